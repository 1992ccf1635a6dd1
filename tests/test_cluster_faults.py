"""Dask under faults (issue 47, item 4): a scheduler address where no Dask scheduler
answers is refused after a timeout with a clear message, never a hang; ``workers`` is
bounded by the usable cores and the memory budget is divided between them; the workers of
a LocalCluster do not outlive a client killed by SIGKILL (the OOM killer's signal). Hangs
are caught by alarms and subprocess timeouts, never by timing assertions."""
import contextlib
import os
import re
import select
import signal
import socket
import subprocess
import sys
import textwrap
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

import clcurv
from tests.hostile import deadline
from clcurv.cli import main as cli
from clcurv.tiles import workers as cluster

distributed = pytest.importorskip("distributed")


@contextlib.contextmanager
def silent_server():
    """The tcp:// address of a server that accepts connections and never says a word."""
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(16)
    held, stop = [], threading.Event()

    def accept():
        srv.settimeout(0.2)
        while not stop.is_set():
            try:
                held.append(srv.accept()[0])
            except OSError:
                pass
    thread = threading.Thread(target=accept, daemon=True)
    thread.start()
    try:
        yield f"tcp://127.0.0.1:{srv.getsockname()[1]}"
    finally:
        stop.set()
        thread.join()
        for c in held:
            c.close()
        srv.close()


def free_address():
    """A tcp:// address where nothing listens."""
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return f"tcp://127.0.0.1:{port}"


# --------------------------------------------------------------------------- --scheduler


@pytest.mark.parametrize("where", ["silent", "nothing"])
def test_an_address_without_a_scheduler_times_out(where):
    with contextlib.ExitStack() as stack:
        addr = stack.enter_context(silent_server()) if where == "silent" else free_address()
        with deadline(30), pytest.raises(cluster.SchedulerError) as exc:
            cluster.connect(addr, timeout=2)
    assert isinstance(exc.value, ConnectionError)
    assert f"no Dask scheduler answered at {addr} within 2 s" in str(exc.value)


@pytest.mark.parametrize("command", ["compute", "features"])
def test_the_command_refuses_a_scheduler_that_says_nothing(tmp_path, capsys, monkeypatch,
                                                           command):
    """``--scheduler`` at a plain TCP server: exit 3 with the reason after
    CONNECT_TIMEOUT, before any point is read or written (it hung for ever)."""
    monkeypatch.setattr(cluster, "CONNECT_TIMEOUT", 2.0)
    src = tmp_path / "p.npy"
    np.save(src, np.random.default_rng(0).random((500, 3)))
    with silent_server() as addr, deadline(60):
        code = cli.main([command, str(src), "-o", str(tmp_path / "o.npz"), "--radius", "0.2",
                         "--scheduler", addr, "-q"])
    err = capsys.readouterr().err
    assert code == cli.EXIT_IO, err
    assert re.search(f"error: no Dask scheduler answered at {re.escape(addr)} within 2 s", err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.npy"]


def test_a_scheduler_still_connects():
    lc = distributed.LocalCluster(n_workers=1, processes=False, dashboard_address=None)
    try:
        with deadline(60):
            client = cluster.connect(lc.scheduler_address, timeout=5)
            assert client.submit(lambda x: x + 1, 1).result() == 2
            client.close()
    finally:
        lc.close()


# --------------------------------------------------------------------------- --workers


def test_workers_are_bounded_by_the_usable_cores(monkeypatch):
    monkeypatch.setattr(cluster, "usable_cores", lambda: 2)
    monkeypatch.delenv(cluster.FORCE_WORKERS, raising=False)
    with pytest.warns(RuntimeWarning, match="16 workers asked for, but this process may run "
                      "on 2 core"):
        assert cluster.bound_workers(16) == 2
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert cluster.bound_workers(2) == 2
        monkeypatch.setenv(cluster.FORCE_WORKERS, "1")
        assert cluster.bound_workers(16) == 16
    for bad in (0, -1, 1.5, True, "2"):
        with pytest.raises(ValueError, match="workers must be an integer >= 1"):
            cluster.bound_workers(bad)
    assert cluster.usable_cores() >= 1


def test_the_budget_is_divided_between_the_workers(monkeypatch):
    monkeypatch.setattr(cluster, "usable_cores", lambda: 8)
    assert cluster.worker_budget(1000) == 1000                      # one process
    assert cluster.worker_budget(1000, 4) == 250                    # 4 tiles at once
    assert cluster.worker_budget(1000, 4, client=object()) == 1000  # each worker's own
    monkeypatch.setattr(cluster, "usable_cores", lambda: 2)
    with pytest.warns(RuntimeWarning):
        assert cluster.worker_budget(1000, 4) == 500                # 2 workers started


def test_a_local_cluster_starts_at_most_the_usable_cores(monkeypatch):
    monkeypatch.setattr(cluster, "usable_cores", lambda: 1)
    monkeypatch.delenv(cluster.FORCE_WORKERS, raising=False)
    with deadline(120), pytest.warns(RuntimeWarning, match="starting 1"):
        lc, client = cluster.local_cluster(3)
    try:
        assert len(client.scheduler_info()["workers"]) == 1
    finally:
        client.close()
        lc.close()


def test_the_command_takes_only_a_positive_worker_count(tmp_path, capsys):
    for bad in ("0", "-2", "two"):
        with pytest.raises(SystemExit) as done:
            cli.main(["compute", str(tmp_path / "p.npy"), "-o", str(tmp_path / "o.npz"),
                      "--radius", "1", "--workers", bad])
        assert done.value.code == 2
        assert "argument --workers: must be an integer >= 1" in capsys.readouterr().err


# --------------------------------------------------------------------------- orphans

_CLIENT = textwrap.dedent("""
    import os, sys, time
    sys.path.insert(0, {root!r})                # this checkout's clcurv
    if __name__ == "__main__":
        from clcurv.tiles import workers as cluster
        lc, client = cluster.local_cluster(2)
        print(" ".join(map(str, client.run(os.getpid).values())), flush=True)
        time.sleep(600)
""")


def _alive(pid):
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"     # a zombie is dead
    except OSError:
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_workers_die_with_a_client_killed_by_sigkill(tmp_path):
    """An OOM kill of the client (SIGKILL, nothing runs in it) leaves no worker process."""
    script = tmp_path / "client.py"
    script.write_text(_CLIENT.format(root=str(Path(clcurv.__file__).resolve().parent.parent)))
    env = dict(os.environ, **{cluster.FORCE_WORKERS: "1"})        # 2 workers on any machine
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True, env=env)
    workers = []
    try:
        ready, _, _ = select.select([proc.stdout], [], [], 120)
        assert ready, "the LocalCluster did not start in 120 s"
        workers = [int(p) for p in proc.stdout.readline().split()]
        assert len(workers) == 2 and all(map(_alive, workers))
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
        for _ in range(100):                            # up to 20 s: not a timing, a bound
            if not any(map(_alive, workers)):
                break
            time.sleep(0.2)
        left = [p for p in workers if _alive(p)]
        assert left == [], f"worker processes {left} outlived their client"
    finally:
        proc.kill()
        for p in workers:
            if _alive(p):
                os.kill(p, signal.SIGKILL)


def test_a_run_of_two_workers_sizes_tiles_to_half_the_budget(tmp_path, monkeypatch):
    monkeypatch.setenv(cluster.FORCE_WORKERS, "1")
    s = clcurv.shapes.aerial_scene(20_000, extent=(60.0, 40.0), seed=2)
    src = tmp_path / "s.npy"
    np.save(src, s["points"])
    kw = dict(method="mls2", orient="up")
    budget = 10 << 20            # 20k points in memory take ~12 MB: tiles
    whole = clcurv.curvature_file(src, tmp_path / "a.npz", 1.0, memory=budget, **kw)
    half = clcurv.curvature_file(src, tmp_path / "b.npz", 1.0, memory=budget // 2, **kw)
    with deadline(300):
        two = clcurv.curvature_file(src, tmp_path / "c.npz", 1.0, memory=budget, workers=2,
                                    **kw)
    assert whole["tile_cells"] > half["tile_cells"] == two["tile_cells"]
