"""The ``clcurv`` command line (:mod:`clcurv.cli.main`) and its demo. The top floor."""
