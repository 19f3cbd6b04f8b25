#!/usr/bin/env python3
"""Independent generator of calibration runs for testing `perpend diagnose`.

This file shares no code, no formula source and no constants with the Rust
crates: its geometry (beam/plane intersection), its tracker (a plane fitted
to noisy points by its own least squares), its noise and every effect are
written here from the physics, in functional forms that differ on purpose
from the diagnosis candidates' exact regressors:

| effect            | reading error added (mm)                                   |
|-------------------|------------------------------------------------------------|
| gain              | g_i * (d - d_lo): scale about the range start, not the mean |
| linearity_s       | A_i * sin(pi * x), x = (d - mid) / half-span (S-shaped)      |
| linearity_cubic   | A_i * (x^3 - 0.4 x) (S-shaped cubic, zero-mean-ish)          |
| incidence_tan     | k * tan(gamma), gamma = angle(beam, surface normal)         |
| incidence_sec     | k * (1 / cos(gamma) - 1)                                    |
| crosstalk         | c * (d_prev - d), prev in a scan order drawn per case       |
| thermal_lag       | k_i * (T_sensor - T0), T_sensor lags the logged head T      |
| drift_settle      | A_i * (1 - exp(-t / tau)), exponential settling             |
| ripple            | A * sin(2 pi d / lambda), out of every catalogue            |
| blunder           | the tracker's plane of 2 poses is off by 0.4 mm              |

Off the catalogue (`score.py --offcat`: forms neither this table's
singles nor the diagnosis's candidates have):

| effect / case key | what                                                        |
|-------------------|-------------------------------------------------------------|
| linearity_knee    | A_i * max(0, x - x_i): the slope changes at x_i in [-0.5, 0.5] |
| thermal_lag2      | thermal_lag through two first-order stages (second order)   |
| crosstalk_sq      | c * (d_prev - d) * abs(d_prev - d): carry-over that grows with the step |
| noise: t3         | reading noise Student-t with 3 degrees of freedom (same sd) |
| noise: hetero     | reading noise sd from 0.5x to 1.5x sigma across the range   |
| spatter: n        | n single readings (one sensor of a pose) off by 0.3 mm      |
| missing: n        | n readings left empty                                       |

Temperatures are monotonic (a warm-up, no swing), so thermal and drift are
time-like and may only be told apart when the lag bends the relation.

The v3 block (`score.py --v3`, v3.py: the cases of issue 35), with
`normal_cost` in the case: truth.json then carries what the effects cost
the calibrated normal (`normal_err_deg` over `normal_floor_deg`: the
paper's model's held-out RMS normal error, against the true planes, on the
readings as written and on the same readings with the true effects
removed, same folds), the effects' drawn parameters and `temp_time_r`:

| effect / case key | reading error added (mm), or what                        |
|-------------------|-------------------------------------------------------------|
| incidence_spot    | k * tan(gamma)^2 * cos(phi - psi_i): the spot's stretch, projected on the receiver's azimuth psi_i about the beam (phi: the surface tilt's azimuth); capped at 1 mm over the run |
| gain2             | gain (above) on two of the four sensors                     |
| drift_linear      | A_i * t / t_end                                             |
| thermal_tied      | k_i * (T_head - T_head(0)): the reading tied to the logged head temperature, no lag |
| hysteresis        | -h_i * sign(d - d_prev): the reading lags the sensor's last move (d_prev: its distance at the pose before); h_i = size x 0.6-1.4, not rescaled |
| warmup: plateau   | head temperature T0 + dT tanh(t / tau), tau 0.10-0.15 of the run (plateau from 30-45 % of it) |
| warmup: ramp      | the same, tau 1.0-1.5 runs: the run ends on the rise (|r(T, t)| > 0.98) |
| reversal: N       | poses // N planned poses, each at the last joint's angles 0, 360/N, ... deg (`perpend plan --reversal N`); poses.csv gains joint_deg and base_pose, plan.csv is written |
| tracker_tilt_deg  | [ex, ey]: the tracker reports every plane turned by -eps about the plate's x and y axes (pivot on the spindle axis), so it turns against the head with the joint; truth.json gains `true_planes` |

Issue 46 (power.py: the diagnosis beside the oracle of oracle.py, which
reads `generate_full`'s state: the effects as drawn and every pose's
context):

| effect / case key | reading error added (mm), or what                        |
|-------------------|-------------------------------------------------------------|
| [kind, size, n]   | any effect on n drawn sensors only (`mask`; drawn from its own stream, seed + 19 + j; the others' amplitudes zero, so PHYSICAL caps it by the sensors it is on) |
| tracker_drift     | the tracker's planes drift during the run: turned by s(t) eps about x, y and moved by s(t) D0, s(t) = 1 - exp(-t / tau), tau 0.15-0.6 of the run; written as the distance the calibration's prediction misses along each true beam |
| geometry: skew    | a head neither ring-symmetric nor of one cone: azimuths 20/115/190/300 deg, radii 28-46 mm, cones 15-35 deg |

Usage: gen.py CASE.json OUTDIR   (CASE: the parameters of one run, see
`make_case` in score.py and `make_v3_case` in v3.py) writes
OUTDIR/sensors.csv, OUTDIR/poses.csv (and OUTDIR/plan.csv with `reversal`)
and OUTDIR/truth.json (the hidden truth; the tool under test never reads
it).
Only the standard library is used.
"""

import json
import math
import os
import random
import sys

# --------------------------------------------------------------- vectors


def add(a, b):
    return [a[0] + b[0], a[1] + b[1], a[2] + b[2]]


def sub(a, b):
    return [a[0] - b[0], a[1] - b[1], a[2] - b[2]]


def scale(a, s):
    return [a[0] * s, a[1] * s, a[2] * s]


def dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def cross(a, b):
    return [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]


def norm(a):
    return math.sqrt(dot(a, a))


def unit(a):
    n = norm(a)
    return [a[0] / n, a[1] / n, a[2] / n]


def rot_x(v, t):
    c, s = math.cos(t), math.sin(t)
    return [v[0], c * v[1] - s * v[2], s * v[1] + c * v[2]]


def rot_y(v, t):
    c, s = math.cos(t), math.sin(t)
    return [c * v[0] + s * v[2], v[1], -s * v[0] + c * v[2]]


def tilt(v, ax, ay):
    """Small rotation of a direction by ax about x, then ay about y."""
    return unit(rot_y(rot_x(v, ax), ay))


# --------------------------------------------------------------- heads

# Two head geometries, neither the project's own: the spindle looks along
# +z; zero points sit on a ring, beams lean towards the axis by `cone`.
GEOMETRIES = {
    # ring of 45 mm, sensors at 45/135/225/315 deg, 25 deg cone, zero
    # points 20 mm behind the TCP plane; planes around z = 40 mm.
    "ring45": {"radius": 45.0, "phase": 45.0, "cone": 25.0, "z0": -20.0,
               "standoff": 40.0, "clockwise": False},
    # Tian-like: ring of 30 mm, 20 deg cone, numbered clockwise from +y.
    "tian30": {"radius": 30.0, "phase": 90.0, "cone": 20.0, "z0": 0.0,
               "standoff": 55.0, "clockwise": True},
    # issue 46: a head neither ring-symmetric nor of one cone angle:
    # sensors at 20/115/190/300 deg on radii 28-46 mm, beams leaning
    # 15-35 deg towards the axis.
    "skew": {"radius": [28.0, 40.0, 33.0, 46.0], "azimuth": [20.0, 115.0, 190.0, 300.0],
             "cone": [15.0, 30.0, 22.0, 35.0], "z0": -10.0, "standoff": 45.0},
}


def nominal_head(name):
    """The four (zero point, beam direction) of a geometry: on a ring at
    `phase` + 90 deg steps, or at per-sensor azimuths, radii and cones."""
    g = GEOMETRIES[name]
    sensors = []
    for i in range(4):
        if "azimuth" in g:
            phi = math.radians(g["azimuth"][i])
            radius, cone = g["radius"][i], g["cone"][i]
        else:
            phi = math.radians(g["phase"] + (-90.0 if g["clockwise"] else 90.0) * i)
            radius, cone = g["radius"], g["cone"]
        e = [radius * math.cos(phi), radius * math.sin(phi), g["z0"]]
        c = math.radians(cone)
        u = [-math.sin(c) * math.cos(phi), -math.sin(c) * math.sin(phi), math.cos(c)]
        sensors.append((e, u))
    return sensors


def true_head(nominal, rng, zero_mm, dir_rad):
    out = []
    for e, u in nominal:
        e2 = [x + rng.uniform(-zero_mm, zero_mm) for x in e]
        u2 = tilt(u, rng.uniform(-dir_rad, dir_rad), rng.uniform(-dir_rad, dir_rad))
        out.append((e2, u2))
    return out


# --------------------------------------------------------------- planes


def plane_through(n, p):
    """Plane n.x + d = 0 through p, n unit (towards the head: -z side)."""
    return n, -dot(n, p)


def beam_distance(e, u, plane):
    n, d = plane
    c = dot(n, u)
    return -(dot(n, e) + d) / c


def tracker_fit(plane, rng, xi, points, patch, centre):
    """Plane fitted to `points` noisy points of `plane` on a square patch:
    z = a x + b y + c by ordinary least squares in the plane's own frame
    (normal equations solved by Cramer's rule)."""
    if xi <= 0.0 or points < 3:
        return plane
    n, _ = plane
    t1 = unit(cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0]))
    t2 = cross(n, t1)
    sxx = sxy = syy = sx = sy = sz = sxz = syz = 0.0
    m = float(points)
    for _ in range(points):
        a = rng.uniform(-patch / 2, patch / 2)
        b = rng.uniform(-patch / 2, patch / 2)
        p = add(add(centre, scale(t1, a)), scale(t2, b))
        p = add(p, [rng.gauss(0, xi), rng.gauss(0, xi), rng.gauss(0, xi)])
        q = sub(p, centre)
        x, y, z = dot(q, t1), dot(q, t2), dot(q, n)
        sxx += x * x
        sxy += x * y
        syy += y * y
        sx += x
        sy += y
        sz += z
        sxz += x * z
        syz += y * z
    mat = [[sxx, sxy, sx], [sxy, syy, sy], [sx, sy, m]]
    rhs = [sxz, syz, sz]

    def det3(k):
        return (k[0][0] * (k[1][1] * k[2][2] - k[1][2] * k[2][1])
                - k[0][1] * (k[1][0] * k[2][2] - k[1][2] * k[2][0])
                + k[0][2] * (k[1][0] * k[2][1] - k[1][1] * k[2][0]))

    dm = det3(mat)
    sol = []
    for j in range(3):
        k = [row[:] for row in mat]
        for r in range(3):
            k[r][j] = rhs[r]
        sol.append(det3(k) / dm)
    a, b, c = sol
    # local surface z = a x + b y + c: normal ~ n - a t1 - b t2
    n2 = unit(sub(sub(n, scale(t1, a)), scale(t2, b)))
    p0 = add(centre, scale(n, c))
    return plane_through(n2, p0)


# --------------------------------------------------------------- effects


def effect_error(kind, par, i, ctx):
    """Reading error [mm] of sensor i (0-based) for one effect (nothing on
    a sensor its `mask` leaves out: an effect on some sensors only)."""
    mask = par.get("mask")
    if mask is not None and not mask[i]:
        return 0.0
    d = ctx["d"][i]
    if kind in ("gain", "gain2"):
        return par["g"][i] * (d - ctx["d_lo"][i])
    if kind == "linearity_s":
        x = (d - ctx["mid"][i]) / ctx["half"][i]
        return par["A"][i] * math.sin(math.pi * max(-1.2, min(1.2, x)))
    if kind == "linearity_cubic":
        x = (d - ctx["mid"][i]) / ctx["half"][i]
        return par["A"][i] * (x ** 3 - 0.4 * x)
    if kind == "incidence_tan":
        return par["k"] * math.tan(ctx["gamma"][i])
    if kind == "incidence_sec":
        return par["k"] * (1.0 / math.cos(ctx["gamma"][i]) - 1.0)
    if kind == "crosstalk":
        order = par["order"]
        pos = order.index(i)
        prev = order[pos - 1]  # the first in a scan follows the last of the previous scan
        return par["c"] * (ctx["d"][prev] - d)
    if kind == "thermal_lag":
        return par["k"][i] * (ctx["t_sensor"] - ctx["T0"])
    if kind == "thermal_lag2":
        return par["k"][i] * (ctx["t_sensor2"] - ctx["T0"])
    if kind == "linearity_knee":
        x = (d - ctx["mid"][i]) / ctx["half"][i]
        return par["A"][i] * max(0.0, x - par["xk"][i])
    if kind == "crosstalk_sq":
        order = par["order"]
        step = ctx["d"][order[order.index(i) - 1]] - d
        return par["c"] * step * abs(step)
    if kind == "drift_settle":
        return par["A"][i] * (1.0 - math.exp(-ctx["t"] / par["tau"]))
    if kind == "ripple":
        return par["A"] * math.sin(2 * math.pi * d / par["lam"] + par["ph"][i])
    return v3_error(kind, par, i, ctx)


def spot_form(n, u, psi):
    """The shape of a triangulation spot's centroid bias on a surface of
    normal `n` seen along beam `u`: the spot stretches as tan^2 of the
    incidence angle, and its centroid moves with the stretch's projection
    on the receiver's azimuth `psi` about the beam (in a frame fixed to
    the beam): tan(gamma)^2 * cos(phi - psi), phi the azimuth of the
    surface's tilt about the beam. Neither 1/cos - 1 nor symmetric."""
    t1 = unit(cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0]))
    t2 = cross(u, t1)
    c = abs(dot(n, u))
    s1, s2 = dot(n, t1), dot(n, t2)
    tan2 = (s1 * s1 + s2 * s2) / max(1e-12, c * c)
    return tan2 * math.cos(math.atan2(s2, s1) - psi)


def v3_error(kind, par, i, ctx):
    """Reading error [mm] of sensor i for the effects of the v3 block
    (`score.py --v3`, the cases of issue 35)."""
    d = ctx["d"][i]
    if kind == "incidence_spot":
        return par["k"] * spot_form(ctx["n"], ctx["u"][i], par["psi"][i])
    if kind == "drift_linear":
        return par["A"][i] * ctx["t"] / ctx["t_end"]
    if kind == "thermal_tied":
        return par["k"][i] * (ctx["T_head"] - ctx["T_head0"])
    if kind == "hysteresis":
        # the reading lags behind the move: low after a move outwards
        prev = ctx["d_prev"]
        sign = par["first"][i] if prev is None else (1.0 if d >= prev[i] else -1.0)
        return -par["h"][i] * sign
    if kind == "tracker_drift":
        return tracker_drift_error(par, i, ctx)
    raise ValueError(kind)


def tracker_drift_error(par, i, ctx):
    """Reading error [mm] of sensor i from a tracker whose planes drift
    during the run (issue 46): at time t the tracker reports every plane
    turned by s(t) A eps (rad, about x and y, pivot on the spindle axis)
    and moved by s(t) A D0 along its normal, s(t) = 1 - exp(-t / tau) (the
    tracker settling: a drift that changes during the run, neither linear
    nor tied to the head's temperature). Written as its reading equivalent:
    the true distance along the true beam to the true plane less that to
    the reported one, what the calibration's prediction misses."""
    s = (1.0 - math.exp(-ctx["t"] / (par["tau_frac"] * ctx["t_end"]))) * par["A"]
    plane = ctx["plane"]
    n2, d2 = reported(plane, [s * par["eps"][0], s * par["eps"][1], 0.0])
    e, u = ctx["e"][i], ctx["u"][i]
    return beam_distance(e, u, plane) - beam_distance(e, u, (n2, d2 + s * par["D0"]))


def reading_noise(case, rng, sd, d, lo, hi):
    """One reading's noise: Gaussian of sd `sd`, or the case's `noise`
    variant (Student-t with 3 degrees of freedom scaled to the same sd; or
    Gaussian whose sd grows from 0.5 sd to 1.5 sd across the range lo..hi)."""
    kind = case.get("noise")
    if kind == "t3":
        chi2 = sum(rng.gauss(0, 1) ** 2 for _ in range(3))
        return sd * rng.gauss(0, 1) / math.sqrt(max(1e-12, chi2 / 3)) / math.sqrt(3)
    if kind == "hetero":
        return rng.gauss(0, sd * (0.5 + (d - lo) / max(1e-9, hi - lo)))
    return rng.gauss(0, sd)


def draw_effect(kind, rng, size_mm, span_mm):
    """Coefficients giving a reading error of about `size_mm` at the range
    ends (signs and per-sensor factors drawn)."""

    def per_sensor():
        return [size_mm * rng.choice([-1, 1]) * rng.uniform(0.6, 1.4) for _ in range(4)]

    if kind == "gain":
        return {"g": [a / span_mm for a in per_sensor()]}
    if kind in ("linearity_s", "linearity_cubic"):
        return {"A": per_sensor()}
    if kind == "linearity_knee":
        return {"A": per_sensor(), "xk": [rng.uniform(-0.5, 0.5) for _ in range(4)]}
    if kind in ("incidence_tan", "incidence_sec"):
        return {"k": None, "size": size_mm}  # scaled once the angles are known
    if kind in ("crosstalk", "crosstalk_sq"):
        order = list(range(4))
        if rng.random() < 0.5:
            rng.shuffle(order)
        return {"c": None, "size": size_mm, "order": order}
    if kind in ("thermal_lag", "thermal_lag2"):
        return {"k": None, "size": size_mm, "signs": per_sensor()}
    if kind == "drift_settle":
        return {"A": per_sensor(), "tau": rng.uniform(600.0, 2400.0)}
    if kind == "ripple":
        return {"A": size_mm, "lam": rng.uniform(0.8, 2.0),
                "ph": [rng.uniform(0, 2 * math.pi) for _ in range(4)]}
    if kind == "gain2":
        which = rng.sample(range(4), 2)
        return {"g": [a / span_mm if i in which else 0.0 for i, a in enumerate(per_sensor())]}
    if kind == "incidence_spot":
        return {"k": None, "size": size_mm, "psi": [rng.uniform(0, 2 * math.pi) for _ in range(4)]}
    if kind == "drift_linear":
        return {"A": per_sensor()}
    if kind == "thermal_tied":
        return {"k": None, "size": size_mm, "signs": per_sensor()}
    if kind == "tracker_drift":
        # A scales the whole drift (offset D0 mm, tilt eps rad: about the
        # size at the spots of a 40 mm ring); tau a fraction of the run
        return {"A": 1.0, "D0": size_mm * rng.choice([-1, 1]) * rng.uniform(0.6, 1.4),
                "eps": [size_mm / 40.0 * rng.gauss(0, 1) for _ in range(2)],
                "tau_frac": rng.uniform(0.15, 0.6)}
    if kind == "hysteresis":
        # not rescaled: h is the size asked for (x0.6-1.4 per sensor)
        return {"h": [size_mm * rng.uniform(0.6, 1.4) for _ in range(4)],
                "first": [rng.choice([-1.0, 1.0]) for _ in range(4)]}
    raise ValueError(kind)


# Largest effect drawn: a poor sensor or head, several times what the
# datasheets of triangulation sensors allow, and inside the diagnosis's
# own plausibility bounds (so a miss is a miss, not a refusal).
PHYSICAL = {
    "gain": 0.05,            # |g| <= 5 % of reading
    "linearity": 0.005,      # amplitude <= 0.5 % of the run's span
    "incidence": 0.10,       # bias change over the run <= 100 um
    "crosstalk": 0.10,       # carry-over <= 10 %
    "thermal": 0.020,        # <= 20 um/C
    "drift": 0.10,           # settling amplitude <= 100 um
    "ripple": 0.03,          # <= 30 um
    # the v3 spot bias: up to 1 mm over the run (a shiny or rough surface
    # at 20-40 deg of incidence; an effect the geometry absorbs mostly)
    "incidence_spot": 1.0,
}


def physical_cap(kind, par, span, gammas, temps):
    """The largest factor on the effect's current size that stays within
    PHYSICAL."""
    def cap(value, limit):
        return limit / value if value > 1e-15 else float("inf")

    if kind in ("gain", "gain2"):
        return cap(max(abs(g) for g in par["g"]), PHYSICAL["gain"])
    if kind == "incidence_spot":
        return cap(abs(par["k"]) * par["range"], PHYSICAL["incidence_spot"])
    if kind.startswith("linearity"):
        return cap(max(abs(a) for a in par["A"]), PHYSICAL["linearity"] * span)
    if kind.startswith("incidence"):
        f = math.tan if kind == "incidence_tan" else (lambda x: 1 / math.cos(x) - 1)
        v = [f(g) for g in gammas]
        return cap(abs(par["k"]) * (max(v) - min(v)), PHYSICAL["incidence"])
    if kind == "crosstalk":
        return cap(par["c"], PHYSICAL["crosstalk"])
    if kind == "crosstalk_sq":
        # the carry-over's share at the largest step
        return cap(par["c"] * par["step_max"], PHYSICAL["crosstalk"])
    if kind in ("thermal_lag", "thermal_lag2", "thermal_tied"):
        return cap(max(abs(k) for k in par["k"]), PHYSICAL["thermal"])
    if kind in ("drift_settle", "drift_linear"):
        return cap(max(abs(a) for a in par["A"]), PHYSICAL["drift"])
    if kind == "ripple":
        return cap(abs(par["A"]), PHYSICAL["ripple"])
    return float("inf")


def rescale(kind, par, f):
    """Multiplies an effect's size by f."""
    for key in ("g", "A", "k", "c"):
        v = par.get(key)
        if isinstance(v, list):
            par[key] = [x * f for x in v]
        elif isinstance(v, float):
            par[key] = v * f


# --------------------------------------------------------------- refit


def solve(a, b):
    """Gaussian elimination with partial pivoting (small dense systems)."""
    n = len(b)
    m = [row[:] + [b[i]] for i, row in enumerate(a)]
    for c in range(n):
        p = max(range(c, n), key=lambda r: abs(m[r][c]))
        if abs(m[p][c]) < 1e-300:
            return None
        m[c], m[p] = m[p], m[c]
        for r in range(c + 1, n):
            f = m[r][c] / m[c][c]
            for k in range(c, n + 1):
                m[r][k] -= f * m[c][k]
    x = [0.0] * n
    for r in range(n - 1, -1, -1):
        x[r] = (m[r][n] - sum(m[r][k] * x[k] for k in range(r + 1, n))) / m[r][r]
    return x


def gauss_newton(model, npar, target, iters, step_of, damped):
    """Parameters (from 0) of `model` (parameters -> predictions) that best
    fit `target`: `iters` Gauss-Newton steps with forward differences of
    step `step_of(j)`; `damped` halves a step that does not lower the
    residual sum of squares (and stops when 30 halvings do not)."""
    p = [0.0] * npar
    for _ in range(iters):
        f0 = model(p)
        r = [t - f for t, f in zip(target, f0)]
        jac = []
        for j in range(npar):
            h = step_of(j)
            q = p[:]
            q[j] += h
            jac.append([(a - b) / h for a, b in zip(model(q), f0)])
        ata = [[sum(x * y for x, y in zip(jac[a], jac[b])) for b in range(npar)] for a in range(npar)]
        atr = [sum(x * y for x, y in zip(jac[a], r)) for a in range(npar)]
        step = solve(ata, atr)
        if step is None:
            break
        if damped:
            rss0 = sum(x * x for x in r)
            for _ in range(30):
                q = [a + b for a, b in zip(p, step)]
                if sum((t - f) ** 2 for t, f in zip(target, model(q))) <= rss0:
                    break
                step = [x / 2 for x in step]
            else:
                break
        p = [a + b for a, b in zip(p, step)]
    return p


def refit(e, u, planes, target, damped=False):
    """The best zero point + beam direction (5 parameters: E moves in 3-D,
    u tilts about two axes normal to it) for readings `target` of `planes`
    (Gauss-Newton, numerical derivatives): returns (E, u). `damped` halves
    a step that does not lower the residual sum of squares (noisy data and
    few poses; noise-free refits converge without)."""
    t1 = unit(cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0]))
    t2 = cross(u, t1)

    def head(p):
        return add(e, p[:3]), unit(add(add(u, scale(t1, p[3])), scale(t2, p[4])))

    def model(p):
        e2, u2 = head(p)
        return [beam_distance(e2, u2, pl) for pl in planes]

    return head(gauss_newton(model, 5, target, 6, lambda j: 1e-6 if j < 3 else 1e-8, damped))


def refit_residuals(e, u, planes, target):
    """Residuals of `target` after the best zero point + beam direction."""
    e2, u2 = refit(e, u, planes, target)
    return [t - beam_distance(e2, u2, pl) for t, pl in zip(target, planes)]


def heldout_fit(head, planes, target, skip, rng):
    """Every sensor's zero point and direction fitted by k-fold
    cross-validation by pose to the readings `target` of `planes` (the
    poses in `skip`, the blunders, left out). k follows the diagnosis's
    documented convention: 10 folds below 100 poses (at most half the
    poses, at least 5), 5 from 100 on; the folds are drawn from `rng`.
    Returns (fold of each kept pose, the fitted head of each fold)."""
    keep = [j for j in range(len(planes)) if j not in skip]
    k = max(5, min(10, len(keep) // 2)) if len(keep) < 100 else 5
    order = keep[:]
    rng.shuffle(order)
    fold = {j: n % k for n, j in enumerate(order)}
    heads = []
    for f in range(k):
        train = [j for j in keep if fold[j] != f]
        fitted = []
        for i, (e, u) in enumerate(head):
            tr = [j for j in train if target[j][i] is not None]
            fitted.append(refit(e, u, [planes[j] for j in tr], [target[j][i] for j in tr],
                                damped=True))
        heads.append(fitted)
    return fold, heads


def oracle_heldout(head, planes, target, skip, rng, fit=None):
    """The floor on these very draws, held out as the diagnosis holds out:
    readings with the true effects removed (`target`), every sensor's zero
    point and direction fitted on k-1 folds of the poses (`heldout_fit`)
    and each held-out reading predicted. What a calibration that knew the
    effects exactly would achieve on this run. Returns the held-out
    residual of every pose and sensor (None for `skip` and for missing
    readings) and the fit (`fit`, when given, is used instead of
    fitting again)."""
    fold, heads = fit if fit is not None else heldout_fit(head, planes, target, skip, rng)
    out = [[None] * len(head) for _ in planes]
    for j, f in fold.items():
        for i, (e2, u2) in enumerate(heads[f]):
            if target[j][i] is not None:
                out[j][i] = target[j][i] - beam_distance(e2, u2, planes[j])
    return out, (fold, heads)


def visible_rms(head, planes, true_d, errs):
    """RMS of an effect's noise-free reading error left after the best
    geometric refit of every sensor."""
    acc, n = 0.0, 0
    for i, (e, u) in enumerate(head):
        target = [true_d[k][i] + errs[k][i] for k in range(len(planes))]
        res = refit_residuals(e, u, planes, target)
        acc += sum(x * x for x in res)
        n += len(res)
    return math.sqrt(acc / max(1, n))


# --------------------------------------------------------------- a run


def damage(case, rows, clean, blunders):
    """The case's `spatter` (single readings off by 0.3 mm, on poses
    without a blunder) and `missing` readings (emptied), drawn from their
    own stream so that the rest of the run is the same draw without them.
    Returns the spattered poses (0-based)."""
    extra = random.Random(case["seed"] + 13)
    spatter = set()
    for _ in range(case.get("spatter", 0)):
        k = extra.choice([j for j in range(len(rows)) if j not in blunders | spatter])
        i = extra.randrange(4)
        rows[k]["reads"][i] += 0.3 * extra.choice([-1, 1])
        spatter.add(k)
    for _ in range(case.get("missing", 0)):
        k, i = extra.randrange(len(rows)), extra.randrange(4)
        rows[k]["reads"][i] = None
        clean[k][i] = None
    return spatter


def generate_full(case):
    """One run (see `generate`) and the generator's state that the oracle
    of oracle.py reads: the true head, the effects as drawn (kind,
    parameters), every pose's context (true distances, angles,
    temperatures, times, true plane) and the poses left out (blunders,
    spatter)."""
    rng = random.Random(case["seed"])
    geom = case["geometry"]
    g = GEOMETRIES[geom]
    nominal = nominal_head(geom)
    truth = true_head(nominal, rng, 1.0, 0.035)
    sigma = case["sigma_mm"]
    sig_i = [sigma * rng.uniform(0.7, 1.3) for _ in range(4)]
    n_poses = case["poses"]
    spread = math.radians(case["spread_deg"])
    std_range = case.get("standoff_range_mm", 6.0)
    xi = 0.02 * case.get("tracker_factor", 1.0)

    # poses: tilt about x and y, standoff along the axis
    planes, times, frame = [], [], None
    t = 0.0
    if case.get("reversal"):
        planes, times, frame = reversal_poses(case, rng, g["standoff"], spread, std_range)
    for _ in range(0 if frame else n_poses):
        ax, ay = rng.uniform(-spread, spread), rng.uniform(-spread, spread)
        n = tilt([0.0, 0.0, -1.0], ax, ay)
        s = g["standoff"] + rng.uniform(-std_range / 2, std_range / 2)
        planes.append(plane_through(n, [0.0, 0.0, s]))
        t += rng.uniform(20.0, 45.0)
        times.append(t)
    n_poses = len(planes)
    t_end = times[-1]
    # head temperature: warm-up (monotonic), logged with 0.05 C noise
    T0 = rng.uniform(20.0, 23.0)
    dT = rng.uniform(4.0, 9.0)
    tau_h = rng.uniform(0.4, 0.9) * t_end
    tau_lag = rng.uniform(0.15, 0.35) * t_end
    head_T, sensor_T, sensor_T2 = [], [], []
    ts = ts2 = T0
    prev_t = 0.0
    for t in times:
        th = T0 + dT * (1.0 - math.exp(-t / tau_h))
        # first-order lag of the sensor body behind the head (exact step)
        a = math.exp(-(t - prev_t) / tau_lag)
        ts = a * ts + (1 - a) * th
        # a second stage of the same time constant behind the first
        ts2 = a * ts2 + (1 - a) * ts
        prev_t = t
        head_T.append(th)
        sensor_T.append(ts)
        sensor_T2.append(ts2)
    if case.get("warmup"):
        head_T, dT = warmup(case, times)

    true_d = [[beam_distance(e, u, p) for (e, u) in truth] for p in planes]
    gam = [[math.acos(min(1.0, abs(dot(p[0], u)))) for (_, u) in truth] for p in planes]
    d_lo = [min(r[i] for r in true_d) for i in range(4)]
    d_hi = [max(r[i] for r in true_d) for i in range(4)]
    span = max(1e-6, max(d_hi[i] - d_lo[i] for i in range(4)))
    mid = [(d_lo[i] + d_hi[i]) / 2 for i in range(4)]
    half = [max(1e-6, (d_hi[i] - d_lo[i]) / 2) for i in range(4)]

    def context(k):
        return {"d": true_d[k], "d_lo": d_lo, "mid": mid, "half": half, "gamma": gam[k],
                "t": times[k], "t_sensor": sensor_T[k], "t_sensor2": sensor_T2[k],
                "T0": sensor_T[0], "n": planes[k][0], "u": [u for _, u in truth],
                "t_end": t_end, "T_head": head_T[k], "T_head0": head_T[0],
                "d_prev": true_d[k - 1] if k else None,
                "e": [e for e, _ in truth], "plane": planes[k]}

    effects, visible = [], []
    for j, spec in enumerate(case["effects"]):
        kind, size = spec[0], spec[1]
        par = draw_effect(kind, rng, size, span)
        if len(spec) > 2 and spec[2]:
            # on `spec[2]` sensors only, drawn from a stream of their own
            on = random.Random(case["seed"] + 19 + j).sample(range(4), spec[2])
            par["mask"] = [int(i in on) for i in range(4)]
        if kind in ("incidence_tan", "incidence_sec"):
            f = (lambda x: math.tan(x)) if kind == "incidence_tan" else (lambda x: 1 / math.cos(x) - 1)
            vals = [f(x) for r in gam for x in r]
            par["k"] = size / max(1e-9, max(vals) - min(vals)) * rng.choice([-1, 1])
        if kind in ("crosstalk", "crosstalk_sq"):
            diffs = [abs(r[par["order"][j - 1]] - r[par["order"][j]]) for r in true_d for j in range(4)]
        if kind == "crosstalk":
            # the size is the carry-over's typical error: c * |d_prev - d|
            par["c"] = min(0.3, size / max(1e-9, sum(diffs) / len(diffs)))
        if kind == "crosstalk_sq":
            par["step_max"] = max(diffs)
            par["c"] = size / max(1e-12, sum(x * x for x in diffs) / len(diffs))
        if kind in ("thermal_lag", "thermal_lag2"):
            lagged = sensor_T if kind == "thermal_lag" else sensor_T2
            rise = max(1e-9, lagged[-1] - lagged[0])
            par["k"] = [s / rise for s in par["signs"]]
        v3_setup(kind, par, size, rng, [context(k) for k in range(n_poses)])
        if "mask" in par:
            # per-sensor amplitudes of the sensors left out are nothing
            # (so that PHYSICAL caps the effect by the sensors it is on)
            for key in ("g", "A", "k", "h"):
                if isinstance(par.get(key), list):
                    par[key] = [x * m for x, m in zip(par[key], par["mask"])]
        effects.append((kind, par))

    # Scale every effect so that what the paper's model cannot absorb (the
    # RMS of its noise-free error after the best refit of zero points and
    # beam directions, `visible_rms`) is the size the case asks for: an
    # effect the geometry absorbs whole does not bias the calibration
    # within the run and cannot be seen by any diagnosis.
    for j, (kind, par) in enumerate(effects):
        errs = [[effect_error(kind, par, i, context(k)) for i in range(4)] for k in range(n_poses)]
        vis = visible_rms(truth, planes, true_d, errs)
        want = case["effects"][j][1]
        f = want / vis if vis > 1e-12 else 0.0
        if kind == "hysteresis":
            f = 1.0  # sized by h itself
        # ... within what real sensors and heads show (PHYSICAL): an effect
        # the geometry absorbs almost whole stays small and barely visible.
        f = min(f, physical_cap(kind, par, span, [g for r in gam for g in r], sensor_T))
        rescale(kind, par, f)
        visible.append(vis * f)

    blunders = set()
    if case.get("blunders", 0):
        blunders = set(rng.sample(range(n_poses), case["blunders"]))

    n_samples = case.get("n_samples")
    rows, clean = [], []
    for k, p in enumerate(planes):
        ctx = context(k)
        reads, sds = [], []
        for i in range(4):
            err = sum(effect_error(kind, par, i, ctx) for kind, par in effects)
            if n_samples:
                # n samples of per-sample noise sigma*sqrt(n): their mean has sigma
                per = sig_i[i] * math.sqrt(n_samples)
                xs = [rng.gauss(0, per) for _ in range(n_samples)]
                m = sum(xs) / n_samples
                sd = math.sqrt(sum((x - m) ** 2 for x in xs) / (n_samples - 1))
                reads.append(true_d[k][i] + err + m)
                sds.append(sd)
            else:
                reads.append(true_d[k][i] + err + reading_noise(case, rng, sig_i[i], true_d[k][i],
                                                                d_lo[i], d_hi[i]))
        centre = [0.0, 0.0, -p[1] / p[0][2]]
        # with a tracker tilt, the tracker measures the plane it reports
        meas = tracker_fit(reported(p, frame["eps_tcs"][k]) if frame else p, rng, xi, 20, 150.0,
                           centre)
        if k in blunders:
            meas = (meas[0], meas[1] + 0.4 * rng.choice([-1, 1]))
        # the readings less the true effects, for the floor on these draws
        clean.append([reads[i] - sum(effect_error(kind, par, i, ctx) for kind, par in effects)
                      for i in range(4)])
        rows.append({"pose": k + 1, "plane": meas, "reads": reads, "sds": sds,
                     "t": times[k], "T": head_T[k] + rng.gauss(0, 0.05)})
        if frame:
            rows[-1].update({"joint": frame["joint_deg"][k], "base": frame["base_pose"][k]})
    spatter = damage(case, rows, clean, blunders)
    oracle, fit = oracle_heldout(truth, [r["plane"] for r in rows], clean, blunders | spatter,
                                 random.Random(case["seed"] + 11))
    extra = {}
    if case.get("normal_cost"):
        extra = normal_cost(truth, planes, rows, clean, blunders | spatter, fit, case["seed"])
        extra["effect_par"] = [[kind, par] for kind, par in effects]
        extra["temp_time_r"] = correlation(times, head_T)
    if frame:
        extra["tracker_tilt_deg"] = case.get("tracker_tilt_deg", [0.0, 0.0])
        extra["true_planes"] = [[list(n), d] for n, d in planes]
    hidden = {"effects": [list(e) for e in case["effects"]],
              "visible_rms_mm": visible,
              "crosstalk_order": [p.get("order") for _, p in effects if "order" in p],
              "blunder_poses": sorted(b + 1 for b in blunders),
              "spatter_poses": sorted(k + 1 for k in spatter),
              "oracle_heldout_mm": oracle,
              "sigma_mm": sig_i, "tracker_xi_mm": xi,
              "temp_rise_c": dT, "run_s": t_end}
    hidden.update(extra)
    state = {"nominal": nominal, "head": truth, "effects": effects, "contexts": [context(k) for k in range(n_poses)],
             "skip": blunders | spatter}
    return nominal, rows, hidden, state


def generate(case):
    """One run: the nominal head, the rows (pose, reported plane,
    readings, time, temperature) and the hidden truth (`generate_full`
    without its state)."""
    return generate_full(case)[:3]


def rot_z(v, t):
    c, s = math.cos(t), math.sin(t)
    return [c * v[0] - s * v[1], s * v[0] + c * v[1], v[2]]


def rotate(v, w):
    """v turned by the rotation vector w (Rodrigues' formula)."""
    a = norm(w)
    if a < 1e-15:
        return v[:]
    k = scale(w, 1.0 / a)
    return add(add(scale(v, math.cos(a)), scale(cross(k, v), math.sin(a))),
               scale(k, dot(k, v) * (1.0 - math.cos(a))))


def reversal_poses(case, rng, standoff, spread, std_range):
    """Poses of a reversal run (`case["reversal"]` = N joint angles):
    `poses // N` planned tilts and standoffs, each visited at the last
    joint's angles 0, 360/N, ... deg in turn. The head turns by theta about
    its spindle axis (+z), the datum plate does not: in the head's frame
    the plate's normal turns by -theta. A tracker tilt eps (rad, about the
    plate frame's x and y, `case["tracker_tilt_deg"]`) is a rotation fixed
    to the plate; in the head's frame at a pose it is the vector M eps,
    M = Rz(-theta) Ry(ay) Rx(ax) the head-from-plate rotation of that pose,
    so it turns against the head when the joint turns. Returns the true
    planes, the times and the frame data of every pose."""
    n_turn = int(case["reversal"])
    eps = [math.radians(x) for x in case.get("tracker_tilt_deg", [0.0, 0.0])] + [0.0]
    planes, times, joints, bases, eps_tcs = [], [], [], [], []
    t = 0.0
    for b in range(case["poses"] // n_turn):
        ax, ay = rng.uniform(-spread, spread), rng.uniform(-spread, spread)
        s = standoff + rng.uniform(-std_range / 2, std_range / 2)
        for j in range(n_turn):
            theta = 2 * math.pi * j / n_turn
            n = unit(rot_z(rot_y(rot_x([0.0, 0.0, -1.0], ax), ay), -theta))
            planes.append(plane_through(n, [0.0, 0.0, s]))
            eps_tcs.append(rot_z(rot_y(rot_x(eps, ax), ay), -theta))
            joints.append(math.degrees(theta))
            bases.append(b + 1)
            t += rng.uniform(20.0, 45.0)
            times.append(t)
    return planes, times, {"joint_deg": joints, "base_pose": bases, "eps_tcs": eps_tcs}


def reported(plane, eps_tcs):
    """The plane as a tilted tracker reports it: the true one turned by
    -eps_tcs about the point where the spindle axis meets it."""
    n, d = plane
    pivot = [0.0, 0.0, -d / n[2]]
    return plane_through(unit(rotate(n, scale(eps_tcs, -1.0))), pivot)


def warmup(case, times):
    """The head temperature of a v3 warm-up run (`case["warmup"]`), drawn
    from its own stream: T0 + dT * tanh(t / tau), a heater that brings the
    head to a plateau (not the first-order curve the diagnosis's lag
    assumes). "plateau": tau = 0.10-0.15 of the run, the plateau (99.5 %)
    reached by 30-45 % of it, so that a time-linear drift and the
    temperature part ways; "ramp": tau = 1.0-1.5 runs, the run ends on the
    rise and the temperature follows the time (|r| > 0.98). Returns the
    temperatures and the rise dT."""
    wr = random.Random(case["seed"] + 17)
    t0 = wr.uniform(20.0, 23.0)
    dt = wr.uniform(4.0, 9.0)
    frac = {"plateau": (0.10, 0.15), "ramp": (1.0, 1.5)}[case["warmup"]]
    tau = wr.uniform(*frac) * times[-1]
    return [t0 + dt * math.tanh(t / tau) for t in times], dt


def v3_setup(kind, par, size, rng, ctxs):
    """Scales a v3 effect's drawn shape to `size` before the visible
    rescaling of `generate` (as the catalogue's incidence and thermal are)."""
    if kind == "incidence_spot":
        vals = [spot_form(c["n"], c["u"][i], par["psi"][i]) for c in ctxs for i in range(4)]
        par["range"] = max(1e-9, max(vals) - min(vals))
        par["k"] = size / par["range"] * rng.choice([-1, 1])
    if kind == "thermal_tied":
        rise = max(1e-9, abs(ctxs[-1]["T_head"] - ctxs[0]["T_head"]))
        par["k"] = [s / rise for s in par["signs"]]


def correlation(xs, ys):
    """Pearson's r of two equal-length lists."""
    mx, my = sum(xs) / len(xs), sum(ys) / len(ys)
    sxy = sum((x - mx) * (y - my) for x, y in zip(xs, ys))
    sxx = sum((x - mx) ** 2 for x in xs)
    syy = sum((y - my) ** 2 for y in ys)
    return sxy / math.sqrt(max(1e-300, sxx * syy))


def plane_normal(head, reads):
    """The unit normal (z component negative, towards the head) of the
    least-squares plane z = a x + b y + c through the spots e_i + r_i u_i
    of the readings that are there (None when fewer than 3)."""
    pts = [add(e, scale(u, r)) for (e, u), r in zip(head, reads) if r is not None]
    if len(pts) < 3:
        return None
    rows = [[p[0], p[1], 1.0] for p in pts]
    ata = [[sum(r[a] * r[b] for r in rows) for b in range(3)] for a in range(3)]
    atz = [sum(r[a] * p[2] for r, p in zip(rows, pts)) for a in range(3)]
    sol = solve(ata, atz)
    return None if sol is None else unit([sol[0], sol[1], -1.0])


def heldout_normal_deg(fit, true_planes, reads):
    """Angle [deg] between each held-out pose's normal (from its readings
    `reads` and the head of the fold that left it out) and the true
    plane's normal."""
    fold, heads = fit
    out = []
    for j, f in sorted(fold.items()):
        n = plane_normal(heads[f], reads[j])
        if n is not None:
            out.append(math.degrees(math.acos(min(1.0, abs(dot(n, true_planes[j][0]))))))
    return out


def normal_cost(head, true_planes, rows, clean, skip, fit_clean, seed):
    """What the effects cost the calibrated normal on this run: the RMS
    held-out normal error of the paper's model fitted to the readings as
    written (effects in), over the same with the true effects removed (the
    same-draw floor in normal error: the same noise, planes and folds)."""
    meas = [r["plane"] for r in rows]
    reads = [r["reads"] for r in rows]
    fit = heldout_fit(head, meas, reads, skip, random.Random(seed + 11))

    def rms(xs):
        return math.sqrt(sum(x * x for x in xs) / max(1, len(xs)))

    eff = rms(heldout_normal_deg(fit, true_planes, reads))
    floor = rms(heldout_normal_deg(fit_clean, true_planes, clean))
    return {"normal_err_deg": eff, "normal_floor_deg": floor,
            "normal_cost": eff / floor if floor > 0 else float("inf")}


def write(case, out, generated=None):
    """Writes the run of `case` (or `generated`, what `generate` returned
    for it) to the directory `out`."""
    os.makedirs(out, exist_ok=True)
    nominal, rows, truth = generated if generated is not None else generate(case)
    decl = case.get("declared")  # factor on the true sigma, or None: no column
    rng = random.Random(case["seed"] + 7)
    order = list(range(len(rows)))
    if case.get("shuffle"):
        rng.shuffle(order)
    with open(os.path.join(out, "sensors.csv"), "w") as f:
        f.write("# written by host-tests/blind/gen.py (independent of perpend)\n")
        cols = ["sensor", "x_mm", "y_mm", "z_mm", "m", "n", "q"]
        if decl is not None:
            cols.append("sigma_mm")
        f.write(",".join(cols) + "\n")
        for i, (e, u) in enumerate(nominal):
            vals = [str(i + 1)] + ["%.6f" % x for x in e] + ["%.8f" % x for x in u]
            if decl is not None:
                vals.append("%.6f" % (case["sigma_mm"] * decl))
            f.write(",".join(vals) + "\n")
    with open(os.path.join(out, "poses.csv"), "w") as f:
        cols = ["pose", "a", "b", "c", "d_mm", "d1_mm", "d2_mm", "d3_mm", "d4_mm", "t_s", "temp_c"]
        if case.get("n_samples"):
            cols += ["s1_mm", "s2_mm", "s3_mm", "s4_mm", "n_samples"]
        if case.get("reversal"):
            cols += ["joint_deg", "base_pose"]
        f.write(",".join(cols) + "\n")
        for j in order:
            r = rows[j]
            n, d = r["plane"]
            vals = [str(r["pose"])] + ["%.9f" % x for x in n] + ["%.6f" % d]
            vals += ["" if x is None else "%.6f" % x for x in r["reads"]]
            vals += ["%.1f" % r["t"], "%.3f" % r["T"]]
            if case.get("n_samples"):
                vals += ["%.6f" % x for x in r["sds"]] + [str(case["n_samples"])]
            if case.get("reversal"):
                vals += ["%.3f" % r["joint"], str(r["base"])]
            f.write(",".join(vals) + "\n")
    if case.get("reversal"):
        write_plan(rows, os.path.join(out, "plan.csv"))
    truth["case"] = case
    with open(os.path.join(out, "truth.json"), "w") as f:
        json.dump(truth, f, indent=1)


def write_plan(rows, path):
    """The joint angle of every pose, as `perpend plan --reversal` names
    its columns (pose, joint_deg, base_pose), for `perpend cell run
    --reversal --plan`."""
    with open(path, "w") as f:
        f.write("# written by host-tests/blind/gen.py: the joint angle of every pose\n")
        f.write("pose,joint_deg,base_pose\n")
        for r in rows:
            f.write("%d,%.3f,%d\n" % (r["pose"], r["joint"], r["base"]))


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit("usage: gen.py CASE.json OUTDIR")
    with open(sys.argv[1]) as f:
        write(json.load(f), sys.argv[2])
