"""The oracle of the blind bench (issue 46, item 1): the best test of an
effect that knows its true form.

For a run written by gen.py, and for each effect gen.py injected into it,
the oracle fits the calibration model (every sensor's zero point and beam
direction, 5 parameters, as gen.py's `refit`) plus the true form of every
injected effect with a free amplitude on each of the four sensors (the
form is the generator's own `effect_error` with unit amplitude; the oracle
is not told which sensors carry it, nor the amplitudes), by gen.py's
`gauss_newton`, on the planes the tracker reported and the readings as
written, the blunder and spatter poses left out (the oracle knows them).
The tested effect's four amplitudes a are then tested against zero by a
Wald statistic that allows for the noise being correlated across the
sensors of a pose (the tracker's plane error moves all four readings):

    T^2 = a' V^-1 a,  V_ij = S_ij h_i . h_j

with h_i the row of (J_i' J_i)^-1 J_i' of sensor i's amplitude (J_i: the
Jacobian of its fit at the solution, every pose a row) and S the 4 x 4
covariance of the residuals of a pose, estimated from the fit with
nu = n - p degrees of freedom. The reference is Hotelling's
F = (nu - q + 1) / (nu q) T^2 ~ F(q, nu - q + 1), q the sensors tested:
exact for a common design and Gaussian noise, approximate here (the
designs differ per sensor; the model is linearised at the solution), so
power.py checks it on effect-free draws of every regime (the same
statistic, the form drawn as for an effect, the amplitudes zero) and CI
checks that its rejection rate there stays near the level.

The level is the diagnosis's per-candidate level: the family alpha = 0.01
of `perpend diagnose` (crates/perpend-diagnosis/src/diagnose/settings.rs)
over its m candidates (Bonferroni, select.rs), m = 7 in this build
(`candidate_level`). Only the standard library is used; imports gen only.
"""

import math
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import gen  # noqa: E402

# the diagnosis's family level and its catalogue (gain, nonlinearity,
# linearity_table, incidence, crosstalk, thermal, drift)
FAMILY_ALPHA = 0.01
CANDIDATES = 7


def candidate_level(m=CANDIDATES):
    """The level each candidate of the diagnosis is tested at: alpha / m."""
    return FAMILY_ALPHA / max(1, m)


# ------------------------------------------------------------ F distribution


def _betacf(a, b, x):
    """Continued fraction of the incomplete beta function (modified Lentz)."""
    tiny = 1e-300
    qab, qap, qam = a + b, a + 1.0, a - 1.0
    c, d = 1.0, 1.0 - qab * x / qap
    d = 1.0 / (d if abs(d) > tiny else tiny)
    h = d
    for m in range(1, 400):
        m2 = 2 * m
        aa = m * (b - m) * x / ((qam + m2) * (a + m2))
        d = 1.0 + aa * d
        d = 1.0 / (d if abs(d) > tiny else tiny)
        c = 1.0 + aa / c
        c = c if abs(c) > tiny else tiny
        h *= d * c
        aa = -(a + m) * (qab + m) * x / ((a + m2) * (qap + m2))
        d = 1.0 + aa * d
        d = 1.0 / (d if abs(d) > tiny else tiny)
        c = 1.0 + aa / c
        c = c if abs(c) > tiny else tiny
        de = d * c
        h *= de
        if abs(de - 1.0) < 1e-14:
            break
    return h


def betainc(a, b, x):
    """The regularised incomplete beta function I_x(a, b)."""
    if x <= 0.0:
        return 0.0
    if x >= 1.0:
        return 1.0
    ln = (math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b)
          + a * math.log(x) + b * math.log1p(-x))
    if x < (a + 1.0) / (a + b + 2.0):
        return math.exp(ln) * _betacf(a, b, x) / a
    return 1.0 - math.exp(ln) * _betacf(b, a, 1.0 - x) / b


def f_sf(f, d1, d2):
    """P(F > f) for F ~ F(d1, d2)."""
    if f <= 0.0:
        return 1.0
    return betainc(d2 / 2.0, d1 / 2.0, d2 / (d2 + d1 * f))


# ------------------------------------------------------------ forms


def unit_par(kind, par):
    """The effect's parameters with every amplitude 1 and no sensor mask:
    its form as the oracle knows it (shape, time constants, scan order,
    phases), not its size nor where it acts."""
    out = {k: v for k, v in par.items() if k != "mask"}
    for key in ("g", "A", "k", "h", "c"):
        v = out.get(key)
        if isinstance(v, list):
            out[key] = [1.0] * len(v)
        elif isinstance(v, (int, float)) and not isinstance(v, bool):
            out[key] = 1.0
    return out


def form_columns(state, kind, par):
    """The effect's unit form at every pose and sensor: x[k][i]."""
    unit = unit_par(kind, par)
    return [[gen.effect_error(kind, unit, i, ctx) for i in range(4)] for ctx in state["contexts"]]


# ------------------------------------------------------------ the fit


def _jacobian(model, p, step_of):
    f0 = model(p)
    jac = []
    for j in range(len(p)):
        q = p[:]
        q[j] += step_of(j)
        jac.append([(a - b) / step_of(j) for a, b in zip(model(q), f0)])
    return jac, f0


def _inverse(a):
    """Inverse of a small dense matrix (columns by gen.solve), or None."""
    n = len(a)
    cols = []
    for j in range(n):
        c = gen.solve(a, [1.0 if r == j else 0.0 for r in range(n)])
        if c is None:
            return None
        cols.append(c)
    return [[cols[j][r] for j in range(n)] for r in range(n)]


def fit_sensor(e, u, planes, target, cols, iters=8):
    """Zero point + beam direction (gen.refit's 5 parameters) and one
    amplitude per column of `cols` (a list over poses each) fitted to
    `target` by gen.gauss_newton (damped). Returns the amplitudes, the
    residuals, and for each amplitude its row h of (J'J)^-1 J' (over the
    poses), or None where the design is singular."""
    t1 = gen.unit(gen.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0]))
    t2 = gen.cross(u, t1)

    def model(p):
        e2 = gen.add(e, p[:3])
        u2 = gen.unit(gen.add(gen.add(u, gen.scale(t1, p[3])), gen.scale(t2, p[4])))
        out = [gen.beam_distance(e2, u2, pl) for pl in planes]
        for j, c in enumerate(cols):
            out = [o + p[5 + j] * x for o, x in zip(out, c)]
        return out

    def step(j):
        return 1e-6 if j < 3 else 1e-8 if j < 5 else 1.0

    npar = 5 + len(cols)
    p = gen.gauss_newton(model, npar, target, iters, step, True)
    jac, f0 = _jacobian(model, p, step)
    res = [t - f for t, f in zip(target, f0)]
    ata = [[sum(x * y for x, y in zip(jac[a], jac[b])) for b in range(npar)] for a in range(npar)]
    inv = _inverse(ata)
    rows = None
    if inv is not None:
        rows = [[sum(inv[5 + j][a] * jac[a][k] for a in range(npar)) for k in range(len(target))]
                for j in range(len(cols))]
    return p[5:], res, rows


def fit_run(state, rows):
    """The oracle's full model on one run: every sensor fitted with the
    forms of all the run's effects (state["effects"]). Returns per sensor
    (poses used, amplitudes, residuals, h rows) and the parameter count."""
    keep = [k for k in range(len(rows)) if k not in state["skip"]]
    forms = [form_columns(state, kind, par) for kind, par in state["effects"]]
    nominal = state.get("nominal") or state["head"]
    out = []
    for i, (e, u) in enumerate(nominal):
        ks = [k for k in keep if rows[k]["reads"][i] is not None]
        planes = [rows[k]["plane"] for k in ks]
        target = [rows[k]["reads"][i] for k in ks]
        cols = [[f[k][i] for k in ks] for f in forms]
        amps, res, h = fit_sensor(e, u, planes, target, cols)
        out.append({"poses": ks, "amps": amps, "res": res, "h": h})
    return out, 5 + len(forms)


def wald(fits, npar, j):
    """The Wald / Hotelling test of effect j's amplitudes on the sensors
    whose design is regular: {F, df1, df2, p, amps}."""
    use = [i for i, f in enumerate(fits) if f["h"] is not None
           and sum(x * x for x in f["h"][j]) > 0.0 and math.isfinite(sum(f["h"][j]))]
    if not use:
        return {"F": 0.0, "df1": 0, "df2": 0, "p": 1.0, "amps": []}
    idx = [{k: n for n, k in enumerate(fits[i]["poses"])} for i in range(4)]
    common = sorted(set.intersection(*[set(fits[i]["poses"]) for i in use]))
    nu = len(common) - npar
    q = len(use)
    if nu - q + 1 < 1:
        return {"F": 0.0, "df1": q, "df2": 0, "p": 1.0, "amps": []}
    res = {i: [fits[i]["res"][idx[i][k]] for k in common] for i in use}
    s = [[sum(x * y for x, y in zip(res[a], res[b])) / nu for b in use] for a in use]
    v = [[0.0] * q for _ in range(q)]
    for x, a in enumerate(use):
        for y, b in enumerate(use):
            ha, hb = fits[a]["h"][j], fits[b]["h"][j]
            # the pose-wise noise covariance couples only poses both fitted
            dot = sum(ha[idx[a][k]] * hb[idx[b][k]] for k in fits[a]["poses"] if k in idx[b])
            v[x][y] = s[x][y] * dot
    amps = [fits[i]["amps"][j] for i in use]
    w = gen.solve(v, amps)
    if w is None:
        return {"F": 0.0, "df1": q, "df2": nu - q + 1, "p": 1.0, "amps": amps}
    t2 = sum(a * b for a, b in zip(amps, w))
    f = (nu - q + 1) / (nu * q) * t2
    return {"F": f, "df1": q, "df2": nu - q + 1, "p": f_sf(f, q, nu - q + 1), "amps": amps}


def judge_run(state, rows):
    """The oracle's p-value for each of the run's effects, in order."""
    fits, npar = fit_run(state, rows)
    return [wald(fits, npar, j) for j in range(len(state["effects"]))]
