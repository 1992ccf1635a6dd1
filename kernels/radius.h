/* radius.h -- the ball radius of each query point: one radius for the cloud, or with
 * POINT_RADIUS=1 each point's own (the k-NN radius, clcurv/ops/knn_radius.py).
 *
 * Per-point radii reach an operator kernel as squared radii in W (sorted order, padded),
 * the buffer that holds the density weights otherwise: a k-NN ball holds k points by
 * construction, so density weights (1 / #N_r(q)) would be 1 / k everywhere, and the two
 * options exclude each other (clcurv refuses weights='density' with a k-NN radius). Their
 * build option is absent (scale_space.cl) or 0 for a fixed radius.
 *
 *   BALL_R2(W, g, r2)   the squared radius of sorted point g's ball (r2: the fixed one)
 *   BALL_R(W, g, r)     its radius (r: the fixed one), for the constants (2 / r, ...)
 *   POINT_BALL(W, g, ball)  its (r^2, cell) for the neighbour walk (neighbors.h)
 * The MLS2 fit scales its coordinates by the fixed r (par.x, the cloud's largest radius),
 * which cancels out of its curvatures: only the ball changes per point there.
 */
#ifndef CLCURV_RADIUS_H
#define CLCURV_RADIUS_H
#include "common.h"

#if defined(POINT_RADIUS) && POINT_RADIUS
#if DENSITY
#error "per-point radii (POINT_RADIUS) and density weights (DENSITY) share W"
#endif
#define BALL_R2(W, g, r2) ((W)[(g)])
#define BALL_R(W, g, r) sqrt((W)[(g)])
#else
#define BALL_R2(W, g, r2) (r2)
#define BALL_R(W, g, r) (r)
#endif

/* The (r^2, cell) of sorted point g's ball (neighbors.h), from the cloud's ball. */
#define POINT_BALL(W, g, ball) ((REAL2)(BALL_R2(W, g, (ball).x), (ball).y))

#endif
