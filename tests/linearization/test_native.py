"""Native vectorized pose-graph linearization against GTSAM 4.3 and finite differences.

Conventions found in this gtsam wheel (asserted in ``test_gtsam_conventions``): ``Values.retract``
is x·Expmap(ξ) for Pose2 and Pose3 (no Cayley / first-order chart); BetweenFactor's error is
Local(z, xi⁻¹xj) = Logmap(z⁻¹·xi⁻¹·xj); PriorFactor's is Logmap(z⁻¹·x).

GTSAM's own Pose2 Jacobian is not exact at small rotation errors w (``test_gtsam_pose2_jacobian_
discrepancy``; max |A_gtsam − J|/max|J| over random factors, measured here):

    |w|       1e-2     1e-3     1e-4     3e-5     1e-5     1e-6     1e-8     1e-9
    |t_E|=1   3e-11    1e-8     5e-5     3e-3     7e-3     6e-7     1e-8     1e-7
    |t_E|=.01 5e-13    2e-10    5e-7     3e-5     8e-5     5e-7     5e-9     1e-9

(above |w| = 1e-5 Pose2::LogmapDerivative's closed form cancels, error ~ eps·|t|/w²; below it GTSAM
switches to a first-order expansion, error ~ |w|/2; Logmap's error ~ eps·|t|/|w| for 1e-10 < |w|).
The native Jacobians match central differences to ~1e-9 throughout; GTSAM's Pose3 Jacobians are exact.
GTSAM's Pose2 Expmap has the same cancellation (translation error ~ eps·|v|/|ω| for 1e-10 < |ω|).
"""

import os
import pathlib

import gtsam
import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from gtsam_schwarz.linearization import native_kernels as nk
from gtsam_schwarz.linearization.native import NativeLinearizer

DATASETS = pathlib.Path(os.environ.get("GTSAM_SCHWARZ_DATASETS",
                                       pathlib.Path(__file__).resolve().parents[2].parent / "shared" / "datasets"))
N = gtsam.noiseModel
M = gtsam.noiseModel.mEstimator
X = lambda i: gtsam.symbol("x", i)  # noqa: E731
L = lambda i: gtsam.symbol("l", i)  # noqa: E731
P = lambda i: gtsam.symbol("p", i)  # noqa: E731


# ---------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------

def rot3(rng, angle=None):
    w = rng.normal(size=3)
    w *= (rng.uniform(0.1, 3.0) if angle is None else angle) / np.linalg.norm(w)
    return gtsam.Rot3.Expmap(w)


def pose2(rng, scale=3.0):
    return gtsam.Pose2(*(rng.normal(size=3) * [scale, scale, 1.0]))


def pose3(rng, scale=3.0):
    return gtsam.Pose3(rot3(rng), rng.normal(size=3) * scale)


def spd(rng, d):
    A = rng.normal(size=(d, d))
    return A @ A.T + d * np.eye(d)


def noise(kind, d, rng):
    """A noise model of the given kind (Gaussian ones and robust ones on a diagonal base)."""
    base = N.Diagonal.Sigmas(rng.uniform(0.2, 1.0, d))
    if kind == "isotropic":
        return N.Isotropic.Sigma(d, 0.3)
    if kind == "diagonal":
        return base
    if kind == "full":
        return N.Gaussian.Information(spd(rng, d))
    if kind == "unit":
        return N.Unit.Create(d)
    if kind == "constrained":
        return N.Constrained.MixedSigmas(1000.0, np.r_[0.0, np.full(d - 1, 0.5)])
    if kind == "huber-scalar":  # Scalar reweighting: not native, GTSAM linearizes it
        return N.Robust.Create(M.Huber.Create(1.0, M.Huber.ReweightScheme.Scalar), base)
    est = {"huber": lambda: M.Huber.Create(1.3), "cauchy": lambda: M.Cauchy.Create(0.8),
           "tukey": lambda: M.Tukey.Create(4.0), "gemanmcclure": lambda: M.GemanMcClure.Create(1.2),
           "welsch": lambda: M.Welsch.Create(2.5), "dcs": lambda: M.DCS.Create(1.5),
           "fair": lambda: M.Fair.Create(1.4), "deadzone": lambda: M.L2WithDeadZone.Create(0.5),
           "tls": lambda: M.TruncatedLeastSquares.Create(3.0), "null": lambda: M.Null.Create(),
           "asymtukey": lambda: M.AsymmetricTukey.Create(2.0)}[kind]()
    if kind == "cauchy":
        base = N.Gaussian.Information(spd(rng, d))
    elif kind in ("welsch", "tukey"):
        base = N.Isotropic.Sigma(d, 0.4)
    return N.Robust.Create(est, base)


def pose_graph(kind, n, noise_kind, rng, closures=3):
    """A loop of n poses with odometry, a few closures (one reversed, one duplicated) and a prior."""
    g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
    if kind == "pose2":
        for i in range(n):
            v.insert(X(i), pose2(rng))
        Between, Prior, rand = gtsam.BetweenFactorPose2, gtsam.PriorFactorPose2, lambda: pose2(rng, 1.0)
        d = 3
    else:
        for i in range(n):
            v.insert(X(i), pose3(rng))
        Between, Prior, rand = gtsam.BetweenFactorPose3, gtsam.PriorFactorPose3, lambda: pose3(rng, 1.0)
        d = 6
    nk_ = (lambda: noise(noise_kind, d, rng)) if isinstance(noise_kind, str) else noise_kind
    g.add(Prior(X(0), rand(), nk_()))
    for i in range(n - 1):
        g.add(Between(X(i), X(i + 1), rand(), nk_()))
    for c in range(closures):
        a, b = sorted(rng.choice(n, 2, replace=False).tolist())
        g.add(Between(X(b), X(a), rand(), nk_()))      # reversed orientation
    g.add(Between(X(1), X(2), rand(), nk_()))           # duplicate of an odometry pair
    g.add(Between(X(3), X(2), rand(), nk_()))           # duplicate, reversed
    return g, v


def gtsam_hessian(graph, values):
    """GTSAM's H = JᵀJ and g = Jᵀ W r from the dense Hessian of its linearization (sorted-key order)."""
    Lam, eta = graph.linearize(values).hessian()
    return Lam, -np.ravel(eta)


def rel(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-300))


def pose2_close(a: gtsam.Pose2, b: gtsam.Pose2, tol):
    dth = (a.theta() - b.theta() + np.pi) % (2 * np.pi) - np.pi
    return abs(a.x() - b.x()) < tol and abs(a.y() - b.y()) < tol and abs(dth) < tol


# ---------------------------------------------------------------------------------------------
# conventions
# ---------------------------------------------------------------------------------------------

def test_gtsam_conventions():
    """Values.retract = x·Expmap(ξ) (Pose2 (vx, vy, ω), Pose3 (ω, v)); between error = Logmap(z⁻¹xi⁻¹xj)."""
    rng = np.random.default_rng(0)
    for _ in range(5):
        p, xi = pose2(rng), rng.normal(size=3)
        v = gtsam.Values()
        v.insert(1, p)
        vv = gtsam.VectorValues()
        vv.insert(1, xi)
        r = v.retract(vv).atPose2(1)
        assert pose2_close(r, p.compose(gtsam.Pose2.Expmap(xi)), 1e-12)
        assert not pose2_close(r, p.compose(gtsam.Pose2(*xi)), 1e-6)   # not the (x, y, θ) chart
        q, xi6 = pose3(rng), rng.normal(size=6)
        v = gtsam.Values()
        v.insert(1, q)
        vv = gtsam.VectorValues()
        vv.insert(1, xi6)
        r3 = v.retract(vv).atPose3(1)
        assert np.allclose(r3.matrix(), q.compose(gtsam.Pose3.Expmap(xi6)).matrix(), atol=1e-12)
        cay = gtsam.Pose3(q.rotation().compose(gtsam.Rot3.Expmap(xi6[:3])), q.translation() + xi6[3:])
        assert not np.allclose(r3.matrix(), cay.matrix(), atol=1e-6)
    for make, Between, Prior, Log in ((pose2, gtsam.BetweenFactorPose2, gtsam.PriorFactorPose2, gtsam.Pose2.Logmap),
                                      (pose3, gtsam.BetweenFactorPose3, gtsam.PriorFactorPose3, gtsam.Pose3.Logmap)):
        xi, xj, z = make(rng), make(rng), make(rng)
        v = gtsam.Values()
        v.insert(1, xi)
        v.insert(2, xj)
        d = 3 if make is pose2 else 6
        e = Between(1, 2, z, N.Unit.Create(d)).unwhitenedError(v)
        assert np.allclose(e, Log(z.inverse().compose(xi.inverse().compose(xj))), atol=1e-12)
        assert np.allclose(e, z.localCoordinates(xi.between(xj)), atol=1e-12)
        e = Prior(2, z, N.Unit.Create(d)).unwhitenedError(v)
        assert np.allclose(e, Log(z.inverse().compose(xj)), atol=1e-12)


# ---------------------------------------------------------------------------------------------
# retraction
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("kind", ["pose2", "pose3"])
def test_retract_matches_values_retract(kind):
    """state ⊕ x equals values.retract(VectorValues) to 1e-12 for rotations from 0 to ~π
    (Pose2 rotation steps 0 or ≥ 1e-3: GTSAM's own Pose2 Expmap cancels in between, see below)."""
    rng = np.random.default_rng(1)
    graph, values = pose_graph(kind, 40, "diagonal", rng)
    lin = NativeLinearizer(graph, values)
    st = lin.state(values)
    d = 3 if kind == "pose2" else 6
    x = rng.normal(size=lin.dim)
    rot = x.reshape(-1, d)[:, 2 if d == 3 else slice(0, 3)]
    mags = np.array([0.0, 1e-3, 0.1, 1.0, 3.0, 0.0, 2.5, 1e-2])[np.arange(len(rot)) % 8]
    if d == 3:
        rot[:] = np.sign(rot) * mags
    else:
        rot *= (mags / np.linalg.norm(rot, axis=1))[:, None]
        rot[mags == 0] = 0
    new = lin.values(lin.retract(st, x))
    vv = gtsam.VectorValues()
    for v, k in enumerate(lin.keys.tolist()):
        vv.insert(k, x[lin.offsets[v]:lin.offsets[v + 1]])
    ref = values.retract(vv)
    for k in lin.keys.tolist():
        if d == 3:
            assert pose2_close(new.atPose2(k), ref.atPose2(k), 1e-12)
        else:
            assert np.allclose(new.atPose3(k).matrix(), ref.atPose3(k).matrix(), atol=1e-12)


def _vector_values(lin, delta):
    vv = gtsam.VectorValues()
    for k, v in zip(lin.keys.tolist(), delta):
        vv.insert(k, v)
    return vv


@pytest.mark.parametrize("kind", ["pose2", "pose3"])
def test_values_by_retraction_equal_inserted_poses(kind, monkeypatch):
    """A Pose2-only or Pose3-only graph's result Values (the Values read, retracted by the local
    coordinates of the final poses) equals the Values built pose by pose; once the caller changed
    theirs, or where GTSAM's retraction would not give the poses back, the poses are inserted."""
    rng = np.random.default_rng(4)
    graph, values = pose_graph(kind, 60, "diagonal", rng)
    lin = NativeLinearizer(graph, values)
    st = lin.state(values)
    assert lin._base is not None  # the fast path is taken
    x = rng.normal(size=lin.dim) * 2.0  # large steps: rotations up to ~π and beyond
    moved = lin.retract(st, x)
    assert lin._base_unchanged()
    fast = lin.values(moved)
    slow = gtsam.Values()
    lin._insert_poses(slow, moved, None, None)
    if kind == "pose2":
        close = lambda a, b, tol: pose2_close(a.atPose2(k), b.atPose2(k), tol)  # noqa: E731
    else:
        close = lambda a, b, tol: np.allclose(a.atPose3(k).matrix(), b.atPose3(k).matrix(), atol=tol)  # noqa: E731
    for k in lin.keys.tolist():
        assert close(fast, slow, 1e-12)
    if kind == "pose3":  # a chart that does not give the poses back (here: a wrong Log): inserted
        from gtsam_schwarz.linearization import native_kernels
        local = native_kernels.pose3_local
        monkeypatch.setattr(native_kernels, "pose3_local", lambda *a: local(*a) * 1.001)
        assert not lin._same_poses3(values.retract(_vector_values(lin, native_kernels.pose3_local(
            st.R3, st.t3, moved.R3, moved.t3))), moved)
        for k in lin.keys.tolist():
            assert close(lin.values(moved), slow, 1e-14)
        monkeypatch.setattr(native_kernels, "pose3_local", local)
    k0 = lin.keys.tolist()[7]
    values.update(k0, gtsam.Pose2(1e3, -1e3, 0.5) if kind == "pose2"
                  else gtsam.Pose3(gtsam.Rot3.Rz(0.5), np.array([1e3, -1e3, 2.0])))  # the caller's Values changes
    assert not lin._base_unchanged()
    after = lin.values(moved)
    assert fast.size() == slow.size() == after.size() == len(lin.keys)
    for k in lin.keys.tolist():
        assert close(after, slow, 1e-14)


def test_pose2_retract_tiny_rotation_is_accurate():
    """For tiny ω the native Expmap equals its Taylor series to 1e-15; GTSAM's differs by ~eps·|v|/|ω|."""
    rng = np.random.default_rng(2)
    n = 200
    P3 = np.vstack([rng.normal(size=(2, n)), rng.uniform(-3, 3, n)])
    P = nk.pose2_state(*P3)
    v = rng.normal(size=(n, 3))
    v[:, 2] = np.sign(v[:, 2]) * 10.0 ** rng.uniform(-12, -4, n)
    out = nk.pose2_retract(P, v)
    w = v[:, 2]
    A, B = 1 - w**2 / 6 + w**4 / 120, w / 2 - w**3 / 24   # sin ω/ω, (1 − cos ω)/ω
    tx, ty = A * v[:, 0] - B * v[:, 1], B * v[:, 0] + A * v[:, 1]
    c, s = P[2], P[3]
    assert np.allclose(out[0], P[0] + c * tx - s * ty, atol=1e-15, rtol=0)
    assert np.allclose(out[1], P[1] + s * tx + c * ty, atol=1e-15, rtol=0)
    worst = 0.0
    for k in range(n):
        r = gtsam.Pose2(*P3[:, k]).compose(gtsam.Pose2.Expmap(v[k]))
        worst = max(worst, abs(r.x() - out[0, k]), abs(r.y() - out[1, k]))
    assert worst < 1e-5   # GTSAM's cancellation (measured ~1e-7 here), not ours


# ---------------------------------------------------------------------------------------------
# Jacobians
# ---------------------------------------------------------------------------------------------

def _pose2_case(rng, mags):
    """Poses xi, xj and measurements z with rotation errors of the given magnitudes (Pose2)."""
    m = len(mags)
    Pi = np.vstack([rng.normal(size=(2, m)) * 3, rng.uniform(-3, 3, m)])
    Z = np.vstack([rng.normal(size=(2, m)), rng.uniform(-3, 3, m)])
    E = np.vstack([rng.normal(size=(2, m)), np.sign(rng.normal(size=m)) * mags])
    xi = [gtsam.Pose2(*Pi[:, k]) for k in range(m)]
    xj = [xi[k].compose(gtsam.Pose2(*Z[:, k])).compose(gtsam.Pose2.Expmap(E[:, k])) for k in range(m)]
    Pj = np.array([[p.x() for p in xj], [p.y() for p in xj], [p.theta() for p in xj]])
    P = np.hstack([Pi, Pj])
    return nk.pose2_state(*P), Z, xi, xj


MAGS = np.array([3.0, 2.0, 1.0, 0.3, 1e-2, 1e-4, 1e-5, 1e-6, 1e-9, 0.0])


@pytest.mark.parametrize("sqrt_info", ["isotropic", "upper"])
@pytest.mark.parametrize("prior", [False, True])
def test_pose2_jacobians_match_finite_differences(prior, sqrt_info):
    """∂e/∂δ through x·Exp(δ): analytic = central differences to 1e-6 relative (rotations 0 … 3 rad);
    the hot path's blocks (both kernels: isotropic translation and general R) are (RJ)ᵀ(RJ)."""
    rng = np.random.default_rng(3)
    m = len(MAGS)
    P, Z, _, _ = _pose2_case(rng, MAGS)
    if sqrt_info == "isotropic":
        R = np.tile(np.array([[2.0], [0.0], [0.0], [2.0], [0.0], [0.5]]), (1, m))
    else:
        R = np.vstack([rng.uniform(1, 2, m), rng.normal(size=(2, m)), rng.uniform(1, 2, m), rng.normal(size=m),
                       rng.uniform(1, 2, m)])
    F = nk.Pose2Factors(j=np.arange(m, 2 * m), z=Z, R=R, i=None if prior else np.arange(m))
    if prior:  # prior factors on xj: z⁻¹xj = (xi z)⁻¹ xj
        zz = [gtsam.Pose2(P[0, k], P[1, k], np.arctan2(P[3, k], P[2, k])).compose(gtsam.Pose2(*Z[:, k]))
              for k in range(m)]
        F = nk.Pose2Factors(j=np.arange(m, 2 * m), z=np.array([[p.x(), p.y(), p.theta()] for p in zz]).T, R=R)
    assert F.iso == (sqrt_info == "isotropic")
    res = nk.pose2_residual(P, F)
    Ji, Jj = nk.pose2_jacobians(F, res)
    e_of = lambda Q: np.stack(nk.pose2_residual(Q, F).e, -1)  # noqa: E731

    def retract_one(which):
        def r(Q, dx):
            v = np.zeros((2 * m, 3))
            v[which] = np.broadcast_to(dx, (m, 3))
            return nk.pose2_retract(Q, v)
        return r
    # one perturbation direction at a time, for every factor at once
    fd_j = np.stack([(e_of(retract_one(slice(m, 2 * m))(P, h)) - e_of(retract_one(slice(m, 2 * m))(P, -h))) / 2e-6
                     for h in np.eye(3) * 1e-6], -1)
    assert rel(Jj, fd_j) < 1e-6
    if not prior:
        fd_i = np.stack([(e_of(retract_one(slice(0, m))(P, h)) - e_of(retract_one(slice(0, m))(P, -h))) / 2e-6
                         for h in np.eye(3) * 1e-6], -1)
        assert rel(Ji, fd_i) < 1e-6
    # the hot path's H blocks are these Jacobians' products
    C = np.empty((6, m)), np.empty((3, m)), np.empty((9, m)), np.empty((6, m)), np.empty((3, m))
    nk.pose2_system(F, res, hjj=tuple(C[0]), gj=tuple(C[1]),
                    **({} if prior else dict(hij=tuple(C[2]), hii=tuple(C[3]), gi=tuple(C[4]))))
    sym = np.array(nk.SYM3)
    Rm = np.zeros((m, 3, 3))
    for k, (a, b) in enumerate(nk.SYM3):
        Rm[:, a, b] = R[k]
    Aj = Rm @ Jj
    we = np.einsum("mij,mj->mi", Rm, np.stack(res.e, -1))
    Hjj = np.einsum("mki,mkj->mij", Aj, Aj)
    assert rel(C[0].T, Hjj[:, sym[:, 0], sym[:, 1]]) < 1e-12
    assert rel(C[1].T, np.einsum("mki,mk->mi", Aj, we)) < 1e-12
    if not prior:
        Ai = Rm @ Ji
        assert rel(C[2].T.reshape(m, 3, 3), np.einsum("mki,mkj->mij", Ai, Aj)) < 1e-12
        Hii = np.einsum("mki,mkj->mij", Ai, Ai)
        assert rel(C[3].T, Hii[:, sym[:, 0], sym[:, 1]]) < 1e-12
        assert rel(C[4].T, np.einsum("mki,mk->mi", Ai, we)) < 1e-12


@pytest.mark.parametrize("prior", [False, True])
def test_pose3_jacobians_match_finite_differences(prior):
    """Pose3 Jacobians (ω, v) = central differences to 1e-6 relative, rotation errors 0 … 3 rad."""
    rng = np.random.default_rng(4)
    m = len(MAGS)
    Ri = np.stack([rot3(rng).matrix() for _ in range(m)])
    ti = rng.normal(size=(m, 3)) * 3
    Zr = np.stack([rot3(rng).matrix() for _ in range(m)])
    Zt = rng.normal(size=(m, 3))
    Er = np.stack([rot3(rng, a).matrix() if a > 0 else np.eye(3) for a in MAGS])
    Et = rng.normal(size=(m, 3))
    Rj = Ri @ Zr @ Er
    tj = ti + np.einsum("mij,mj->mi", Ri, Zt + np.einsum("mij,mj->mi", Zr, Et))
    Rs, ts = np.concatenate([Ri, Rj]), np.concatenate([ti, tj])
    sqrt_info = np.tile(np.eye(6), (m, 1, 1))
    if prior:
        F = nk.Pose3Factors(j=np.arange(m, 2 * m), zR=Ri @ Zr, zt=ti + np.einsum("mij,mj->mi", Ri, Zt), R=sqrt_info)
    else:
        F = nk.Pose3Factors(j=np.arange(m, 2 * m), zR=Zr, zt=Zt, R=sqrt_info, i=np.arange(m))
    res = nk.pose3_residual(Rs, ts, F)
    assert np.allclose(np.linalg.norm(res.e[:, :3], axis=1), MAGS, atol=1e-12)
    Ji, Jj = nk.pose3_jacobians(F, res)

    def fd(sel):
        cols = []
        for h in np.eye(6) * 1e-6:
            v = np.zeros((2 * m, 6))
            v[sel] = h
            a = nk.pose3_residual(*nk.pose3_retract(Rs, ts, v), F).e
            b = nk.pose3_residual(*nk.pose3_retract(Rs, ts, -v), F).e
            cols.append((a - b) / 2e-6)
        return np.stack(cols, -1)
    assert rel(Jj, fd(slice(m, 2 * m))) < 1e-6
    if not prior:
        assert rel(Ji, fd(slice(0, m))) < 1e-6


def test_so3_logmap_matches_gtsam_including_near_pi():
    """Log R = GTSAM's Rot3.Logmap to 1e-13 from 0 to π (axis from the symmetric part near π; ±ω at π)."""
    rng = np.random.default_rng(14)
    for angle in (0.0, 1e-9, 1e-5, 1.0, np.pi - 1e-2, np.pi - 1e-4, np.pi - 1e-7, np.pi):
        axes = rng.normal(size=(20, 3))
        axes /= np.linalg.norm(axes, axis=1, keepdims=True)
        Rs = np.stack([gtsam.Rot3.Expmap(a * angle).matrix() for a in axes])
        ours = nk.so3_logmap(Rs)
        ref = np.stack([gtsam.Rot3.Logmap(gtsam.Rot3(R)) for R in Rs])
        err = np.abs(ours - ref).max(axis=1)
        if angle > 3.14:
            err = np.minimum(err, np.abs(ours + ref).max(axis=1))
        assert err.max() < 1e-13, angle


def _single_factor_A(factor, values):
    """GTSAM's whitened Jacobian of one factor, columns in the factor's key order."""
    return factor.linearize(values).jacobian()[0]


@pytest.mark.parametrize("kind", ["pose2", "pose3"])
def test_jacobians_match_gtsam_where_it_is_exact(kind):
    """Whitened A = [A_i | A_j] equals GTSAM's linearization to 1e-9 (Pose2: |w| ≥ 1e-2; Pose3: all)."""
    rng = np.random.default_rng(5)
    d = 3 if kind == "pose2" else 6
    for noise_kind in ("full", "huber", "cauchy"):
        for mag in ([3.0, 1.0, 0.1, 1e-2] if d == 3 else [3.0, 1.0, 1e-2, 1e-5, 1e-9]):
            g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
            if d == 3:
                xi, z = pose2(rng), pose2(rng, 1.0)
                xj = xi.compose(z).compose(gtsam.Pose2.Expmap(np.r_[rng.normal(size=2), mag]))
                f = gtsam.BetweenFactorPose2(1, 2, z, noise(noise_kind, d, rng))
            else:
                xi, z = pose3(rng), pose3(rng, 1.0)
                xj = xi.compose(z).compose(gtsam.Pose3(rot3(rng, mag), rng.normal(size=3)))
                f = gtsam.BetweenFactorPose3(1, 2, z, noise(noise_kind, d, rng))
            g.add(f)
            v.insert(1, xi)
            v.insert(2, xj)
            lin = NativeLinearizer(g, v)
            st = lin.state(v)
            K = lin._k2 if d == 3 else lin._k3
            F = K.between
            res = (nk.pose2_residual(st.pose2, F) if d == 3 else nk.pose3_residual(st.R3, st.t3, F))
            Ji, Jj = (nk.pose2_jacobians if d == 3 else nk.pose3_jacobians)(F, res)
            Rm = lin._k3.between.R[0] if d == 6 else np.array(noise_sqrt(f.noiseModel()))
            w = 1.0 if res.weight is None else res.weight[0]
            A = np.sqrt(w) * Rm @ np.hstack([Ji[0], Jj[0]])
            assert rel(A, _single_factor_A(f, v)) < 1e-9, (noise_kind, mag)


def noise_sqrt(nm):
    return (nm.noise() if isinstance(nm, N.Robust) else nm).R()


def test_gtsam_pose2_jacobian_discrepancy():
    """GTSAM's BetweenFactorPose2 Jacobian vs the native one (exact, FD-checked) at small rotation
    errors: off by up to ~7e-3 (|t_E| = 1) / ~8e-5 (|t_E| = 0.01) relative near |w| = 1e-5, ≤ 1e-10 at
    |w| ≥ 1e-2 (table in the module docstring)."""
    rng = np.random.default_rng(6)
    worst = {}
    for tnorm in (1.0, 0.01):
        for w in (1e-2, 1e-4, 2e-5, 1e-6):
            for _ in range(5):
                xi, z = pose2(rng, 5.0), pose2(rng, 2.0)
                t = rng.normal(size=2)
                t *= tnorm / np.linalg.norm(t)
                xj = xi.compose(z).compose(gtsam.Pose2.Expmap(np.r_[t, w]))
                f = gtsam.BetweenFactorPose2(1, 2, z, N.Unit.Create(3))
                v = gtsam.Values()
                v.insert(1, xi)
                v.insert(2, xj)
                P = nk.pose2_state([xi.x(), xj.x()], [xi.y(), xj.y()], [xi.theta(), xj.theta()])
                F = nk.Pose2Factors(j=np.array([1]), i=np.array([0]), z=np.array([[z.x()], [z.y()], [z.theta()]]),
                                    R=np.array([[1.0], [0], [0], [1], [0], [1]]))
                Ji, Jj = nk.pose2_jacobians(F, nk.pose2_residual(P, F))
                J = np.hstack([Ji[0], Jj[0]])
                # the native Jacobian is the exact one
                def e_at(dx):
                    Q = nk.pose2_retract(P, dx.reshape(2, 3))
                    return np.stack(nk.pose2_residual(Q, F).e, -1)[0]
                fd = np.stack([(e_at(h) - e_at(-h)) / 2e-6 for h in np.eye(6) * 1e-6], -1)
                assert rel(J, fd) < 1e-6
                key = (tnorm, w)
                worst[key] = max(worst.get(key, 0.0), rel(_single_factor_A(f, v), J))
    assert worst[(1.0, 1e-2)] < 1e-9 and worst[(0.01, 1e-2)] < 1e-9
    assert worst[(1.0, 2e-5)] > 1e-4       # GTSAM's cancellation is real …
    assert max(worst.values()) < 0.1       # … and bounded
    print("max |A_gtsam - J| / max |J| by (|t_E|, |w|):", {k: f"{v:.1e}" for k, v in worst.items()})


# ---------------------------------------------------------------------------------------------
# errors, H, g
# ---------------------------------------------------------------------------------------------

NOISE_KINDS = ["isotropic", "diagonal", "full", "unit", "huber", "cauchy", "tukey", "gemanmcclure", "welsch",
               "dcs", "fair", "deadzone", "tls", "null", "huber-scalar", "asymtukey", "constrained"]


@pytest.mark.parametrize("kind", ["pose2", "pose3"])
def test_factor_errors_match_gtsam(kind):
    """Every factor's error = factor.error(values) to 1e-12 (all noise kinds); total = graph.error."""
    rng = np.random.default_rng(7)
    d = 3 if kind == "pose2" else 6
    g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
    Between = gtsam.BetweenFactorPose2 if d == 3 else gtsam.BetweenFactorPose3
    Prior = gtsam.PriorFactorPose2 if d == 3 else gtsam.PriorFactorPose3
    make = pose2 if d == 3 else pose3
    n = 12
    for i in range(n):
        v.insert(X(i), make(rng))
    for kind_ in NOISE_KINDS:
        for _ in range(4):
            a, b = rng.choice(n, 2, replace=False).tolist()
            scale = rng.choice([0.05, 0.5, 3.0])
            g.add(Between(X(a), X(b), make(rng, scale), noise(kind_, d, rng)))
        if kind_ != "constrained":
            g.add(Prior(X(int(rng.integers(n))), make(rng), noise(kind_, d, rng)))
    lin = NativeLinearizer(g, v)
    assert lin.gtsam_factor_count == 4 * 3 + 1 * 2   # Scalar reweighting, AsymmetricTukey, constrained
    st = lin.state(v)
    ours = lin.factor_errors(st)
    ref = np.array([g.at(k).error(v) for k in range(g.size())])
    assert np.allclose(ours, ref, rtol=1e-12, atol=1e-14)
    assert lin.error(st) == pytest.approx(g.error(v), rel=1e-12)


def _compare_system(graph, values, tol_h=1e-9, tol_g=1e-9):
    lin = NativeLinearizer(graph, values)
    st = lin.state(values)
    system = lin.linearize(st)
    Lam, g = gtsam_hessian(graph, values)
    assert system.H.shape == Lam.shape and system.H.has_sorted_indices
    assert rel(system.H.toarray(), Lam) < tol_h
    assert rel(system.g, g) < tol_g
    assert system.error == pytest.approx(graph.error(values), rel=1e-12)
    return lin, st, system


@pytest.mark.parametrize("kind", ["pose2", "pose3"])
@pytest.mark.parametrize("noise_kind", ["isotropic", "diagonal", "full", "huber", "cauchy", "tukey", "mixed"])
def test_hessian_and_gradient_match_gtsam(kind, noise_kind):
    """H = JᵀJ and g = JᵀW r equal GTSAM's to 1e-9 (random poses: no tiny rotation errors), with
    duplicate and reversed pairs."""
    rng = np.random.default_rng(8)
    if noise_kind == "mixed":
        kinds = ["isotropic", "diagonal", "full", "huber", "welsch", "huber-scalar"]
        nk_ = lambda: noise(kinds[rng.integers(len(kinds))], 3 if kind == "pose2" else 6, rng)  # noqa: E731
    else:
        nk_ = noise_kind
    graph, values = pose_graph(kind, 25, nk_, rng)
    _compare_system(graph, values)


def mixed_graph(rng):
    """Pose2 poses with Point2 landmarks (BearingRange), a Pose3 pair and a custom-noise prior."""
    g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
    n = 8
    for i in range(n):
        v.insert(X(i), pose2(rng))
    g.add(gtsam.PriorFactorPose2(X(0), pose2(rng), noise("diagonal", 3, rng)))
    for i in range(n - 1):
        g.add(gtsam.BetweenFactorPose2(X(i), X(i + 1), pose2(rng, 1.0), noise("full", 3, rng)))
    g.add(gtsam.BetweenFactorPose2(X(5), X(1), pose2(rng, 1.0), noise("huber", 3, rng)))
    for j in (7, 3, 11):
        v.insert(L(j), rng.normal(size=2) * 3)
        for i in rng.choice(n, 3, replace=False).tolist():
            g.add(gtsam.BearingRangeFactor2D(X(i), L(j), gtsam.Rot2(rng.uniform(-3, 3)), rng.uniform(1, 4),
                                             N.Diagonal.Sigmas(np.array([0.1, 0.3]))))
    g.add(gtsam.PriorFactorPoint2(L(7), np.array([1.0, 2.0]), N.Isotropic.Sigma(2, 0.5)))
    for k in (0, 5):
        v.insert(P(k), pose3(rng))
    g.add(gtsam.PriorFactorPose3(P(0), pose3(rng), noise("isotropic", 6, rng)))
    g.add(gtsam.BetweenFactorPose3(P(0), P(5), pose3(rng, 1.0), noise("diagonal", 6, rng)))
    return g, v


def test_mixed_graph_with_landmarks():
    """Pose2 + Point2 landmarks (GTSAM-linearized) + Pose3: H, g, error, retract, values equal GTSAM's."""
    rng = np.random.default_rng(9)
    graph, values = mixed_graph(rng)
    lin, st, _ = _compare_system(graph, values)
    assert lin.gtsam_factor_count == 3 * 3 + 1
    assert lin.geometry(st) is None
    assert lin.prior_vertices is None   # factors GTSAM linearizes: every row of Hz is read
    x = rng.normal(size=lin.dim) * 0.3
    vv = gtsam.VectorValues()
    for v, k in enumerate(lin.keys.tolist()):
        vv.insert(k, x[lin.offsets[v]:lin.offsets[v + 1]])
    ref, ours = values.retract(vv), lin.retract(st, x)
    assert lin.error(ours) == pytest.approx(graph.error(ref), rel=1e-12)
    assert lin.values(ours).equals(ref, 1e-12)
    _compare_system(graph, ref)   # and at the new point
    mask = lin.translation_mask()
    dims = values.dims()
    for v, k in enumerate(lin.keys.tolist()):
        expect = {3: [True, True, False], 2: [True, True], 6: [False] * 3 + [True] * 3}[dims[k]]
        assert mask[lin.offsets[v]:lin.offsets[v + 1]].tolist() == expect


def test_pattern_is_fixed_sorted_and_symmetric():
    """H keeps one CSR pattern (shared index arrays) across states; `diagonal` points at H's diagonal."""
    rng = np.random.default_rng(10)
    graph, values = pose_graph("pose2", 30, "diagonal", rng)
    lin = NativeLinearizer(graph, values)
    st = lin.state(values)
    s1 = lin.linearize(st)
    H1 = s1.H.toarray()
    s2 = lin.linearize(lin.retract(st, rng.normal(size=lin.dim)))
    assert np.array_equal(s1.H.toarray(), H1)   # pooled value arrays are reused only once unreferenced
    assert np.shares_memory(s1.H.indices, s2.H.indices) and np.shares_memory(s1.H.indptr, s2.H.indptr)
    assert s1.H.has_sorted_indices and s2.H.has_canonical_format
    for s in (s1, s2):
        assert abs(s.H - s.H.T).max() < 1e-12 * abs(s.H).max()
        assert np.array_equal(s.H.data[s.diagonal], s.H.diagonal())
    # every entry of every block of coupled variables, nothing else
    nv = len(lin.keys)
    blocks = {(v, v) for v in range(nv)}
    for k in range(graph.size()):
        ks = np.searchsorted(lin.keys, np.asarray(graph.at(k).keys(), dtype=np.uint64)).tolist()
        blocks |= {(a, b) for a in ks for b in ks}
    assert s1.H.nnz == 9 * len(blocks)
    C = s1.H.tocoo()
    assert {(r // 3, c // 3) for r, c in zip(C.row.tolist(), C.col.tolist())} == blocks


# ---------------------------------------------------------------------------------------------
# construction from arrays, geometry, values
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("kind", ["pose2", "pose3"])
def test_from_arrays_equals_graph_construction(kind):
    """from_arrays (information or sqrt information, robust) = the gtsam-graph construction."""
    rng = np.random.default_rng(11)
    d = 3 if kind == "pose2" else 6
    n, m = 15, 22
    keys = rng.permutation(np.arange(100, 100 + n)) * 7
    if d == 3:
        poses = np.column_stack([rng.normal(size=(n, 2)) * 3, rng.uniform(-np.pi, np.pi, n)])
        Z = np.column_stack([rng.normal(size=(m, 2)), rng.uniform(-3, 3, m)])
        zp = np.array([[0.1, 0.2, 0.3]])
    else:
        Rs = np.stack([rot3(rng).matrix() for _ in range(n)])
        poses = np.concatenate([Rs, rng.normal(size=(n, 3, 1))], axis=2)  # (n, 3, 4)
        Z = (np.stack([rot3(rng).matrix() for _ in range(m)]), rng.normal(size=(m, 3)))
        zp = (np.eye(3)[None], np.array([[0.1, 0.2, 0.3]]))
    E = np.stack([rng.choice(keys, 2, replace=False) for _ in range(m)])
    info = np.stack([spd(rng, d) for _ in range(m)])
    prior_info = np.eye(d) * 100.0
    lin_a = NativeLinearizer.from_arrays(kind, keys, poses, E, Z, information=info, robust=("huber", 2.0),
                                         prior_keys=keys[:1], prior_measurements=zp, prior_information=prior_info)
    g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for k in range(n):
        if d == 3:
            v.insert(int(keys[k]), gtsam.Pose2(*poses[k]))
        else:
            v.insert(int(keys[k]), gtsam.Pose3(gtsam.Rot3(poses[k][:, :3]), poses[k][:, 3]))
    for e in range(m):
        nm = N.Robust.Create(M.Huber.Create(2.0), N.Gaussian.Information(info[e]))
        if d == 3:
            g.add(gtsam.BetweenFactorPose2(int(E[e, 0]), int(E[e, 1]), gtsam.Pose2(*Z[e]), nm))
        else:
            g.add(gtsam.BetweenFactorPose3(int(E[e, 0]), int(E[e, 1]), gtsam.Pose3(gtsam.Rot3(Z[0][e]), Z[1][e]), nm))
    if d == 3:
        g.add(gtsam.PriorFactorPose2(int(keys[0]), gtsam.Pose2(*zp[0]), N.Gaussian.Information(prior_info)))
    else:
        g.add(gtsam.PriorFactorPose3(int(keys[0]), gtsam.Pose3(gtsam.Rot3(zp[0][0]), zp[1][0]), N.Gaussian.Information(prior_info)))
    lin_g = NativeLinearizer(g, v)
    sa, sg = lin_a.initial_state(), lin_g.state(v)
    ya, yg = lin_a.linearize(sa), lin_g.linearize(sg)
    assert np.array_equal(lin_a.keys, lin_g.keys) and np.array_equal(lin_a.offsets, lin_g.offsets)
    assert rel(ya.H.toarray(), yg.H.toarray()) < 1e-12 and rel(ya.g, yg.g) < 1e-12
    assert ya.error == pytest.approx(yg.error, rel=1e-12) == g.error(v)
    assert np.allclose(lin_a.factor_errors(sa), [g.at(k).error(v) for k in range(g.size())], rtol=1e-12, atol=0)
    Lam, grad = gtsam_hessian(g, v)
    assert rel(ya.H.toarray(), Lam) < 1e-9 and rel(ya.g, grad) < 1e-9
    assert lin_a.values(sa).equals(v.extract(lin_a.keys.tolist()), 1e-12)  # poses without factors are no variables


@pytest.mark.parametrize("kind", ["pose2", "pose3"])
def test_one_noise_model_for_all_factors_is_kept_once(kind):
    """One information for every between factor (per factor but all equal, or one gtsam noise model
    shared by all): its square root is kept once, broadcast over the factors (no per-factor rows), and H,
    g and the error equal GTSAM's and those of the same information given as one (d, d) matrix."""
    rng = np.random.default_rng(13)
    d = 3 if kind == "pose2" else 6
    shared = N.Gaussian.Information(spd(rng, d))
    graph, values = pose_graph(kind, 12, lambda: shared, rng)
    lin_g = NativeLinearizer(graph, values)
    K = lin_g._k2 if kind == "pose2" else lin_g._k3
    rows = K.between.R[0] if kind == "pose2" else K.between.R
    assert rows.strides[0] == 0 and K.between.size > 1   # one R for all factors, not one per factor
    yg = lin_g.linearize(lin_g.state(values))
    Lam, grad = gtsam_hessian(graph, values)
    assert rel(yg.H.toarray(), Lam) < 1e-9 and rel(yg.g, grad) < 1e-9
    assert yg.error == pytest.approx(graph.error(values), rel=1e-12)
    # from arrays: the same information per factor, and as one (d, d) matrix
    n, m = 9, 14
    keys = np.arange(n)
    if d == 3:
        poses = np.column_stack([rng.normal(size=(n, 2)), rng.uniform(-3, 3, n)])
        Z = np.column_stack([rng.normal(size=(m, 2)), rng.uniform(-3, 3, m)])
    else:
        poses = np.concatenate([np.stack([rot3(rng).matrix() for _ in range(n)]), rng.normal(size=(n, 3, 1))], axis=2)
        Z = (np.stack([rot3(rng).matrix() for _ in range(m)]), rng.normal(size=(m, 3)))
    E = np.stack([rng.choice(keys, 2, replace=False) for _ in range(m)])
    info = spd(rng, d)
    per_factor = NativeLinearizer.from_arrays(kind, keys, poses, E, Z, information=np.repeat(info[None], m, axis=0))
    one = NativeLinearizer.from_arrays(kind, keys, poses, E, Z, information=info)
    for lin in (per_factor, one):
        K = lin._k2 if kind == "pose2" else lin._k3
        assert (K.between.R[0] if kind == "pose2" else K.between.R).strides[0] == 0
    ya, yb = per_factor.linearize(per_factor.initial_state()), one.linearize(one.initial_state())
    assert np.array_equal(ya.H.toarray(), yb.H.toarray()) and np.array_equal(ya.g, yb.g) and ya.error == yb.error


def test_pose2_information_in_runs_is_kept_once_per_run(monkeypatch):
    """Pose2 factors whose information comes in a few long runs (odometry, then closures, then a second
    closure kind) keep one R column per run, and every chunk stays inside one run: the factor errors and
    the arrays of the chordal start equal those of per-factor rows bit for bit, H, g and the error to
    rounding (chunks cut at other places sum the poses' blocks in another order)."""
    rng = np.random.default_rng(21)
    n = 40_000
    m = 3 * n
    keys = np.arange(n)
    poses = np.column_stack([rng.normal(size=(n, 2)), rng.uniform(-3, 3, n)])
    E = np.concatenate([np.column_stack([keys[:-1], keys[1:]]), rng.integers(0, n, size=(m - n + 1, 2))])
    E = E[E[:, 0] != E[:, 1]]
    m = len(E)
    Z = np.column_stack([rng.normal(size=(m, 2)), rng.uniform(-3, 3, m)])
    run = np.repeat([0, 1, 2], [n - 1, 30_000, m - n + 1 - 30_000])   # three informations in runs
    infos = np.stack([spd(rng, 3) for _ in range(3)])
    info = infos[run]

    def build():
        return NativeLinearizer.from_arrays("pose2", keys, poses, E, Z, information=info, prior_keys=[0],
                                            prior_measurements=poses[:1], prior_information=np.eye(3))

    runs = build()
    F = runs._k2.between
    assert F.R is None and len(F._runs[0]) == 3   # three columns kept, not one per factor
    chunks = F.chunks()
    assert all(c.R.strides[1] == 0 for _, _, c in chunks)                    # each chunk inside one run
    monkeypatch.setattr(nk, "_column_runs", lambda R: None)
    rows = build()
    assert rows._k2.between.R is not None
    assert np.array_equal(F.rows(), rows._k2.between.R)
    sel = rng.choice(m, 1000, replace=False)
    assert np.array_equal(F.rows(sel), rows._k2.between.R[:, sel])
    sa, sb = runs.initial_state(), rows.initial_state()
    ya, yb = runs.linearize(sa), rows.linearize(sb)
    assert rel(ya.H.data, yb.H.data) < 1e-14 and rel(ya.g, yb.g) < 1e-14
    assert ya.error == pytest.approx(yb.error, rel=1e-14)
    assert np.array_equal(runs.factor_errors(sa), rows.factor_errors(sb))
    ga, gb = runs.pose_graph(), rows.pose_graph()
    assert np.array_equal(ga["between"]["information"], gb["between"]["information"])


@pytest.mark.parametrize("kind", ["pose2", "pose3"])
def test_geometry_values_and_translation_mask(kind):
    rng = np.random.default_rng(12)
    graph, values = pose_graph(kind, 10, "isotropic", rng)
    lin = NativeLinearizer(graph, values)
    st = lin.state(values)
    geo = lin.geometry(st)
    assert lin.values(st).equals(values, 1e-12)
    for v, k in enumerate(lin.keys.tolist()):
        if kind == "pose2":
            p = values.atPose2(k)
            assert np.allclose(geo.positions[v], [p.x(), p.y()]) and np.allclose(geo.rotations[v], p.rotation().matrix())
        else:
            p = values.atPose3(k)
            assert np.allclose(geo.positions[v], p.translation()) and np.allclose(geo.rotations[v], p.rotation().matrix())
    d = 3 if kind == "pose2" else 6
    expect = [True, True, False] if d == 3 else [False] * 3 + [True] * 3
    assert lin.translation_mask().tolist() == expect * len(lin.keys)
    assert lin.offsets.dtype == np.int64 and lin.keys.dtype == np.uint64
    assert np.array_equal(lin.offsets, np.arange(len(lin.keys) + 1) * d)


# ---------------------------------------------------------------------------------------------
# Gauss–Newton with the native linearizer reaches GTSAM's optimum
# ---------------------------------------------------------------------------------------------

def _gauss_newton(lin, st, iters=30):
    for _ in range(iters):
        system = lin.linearize(st)
        dx = spla.spsolve(sp.csc_matrix(system.H), -system.g)
        st = lin.retract(st, dx)
        if np.linalg.norm(dx) < 1e-12:
            break
    return st


@pytest.mark.parametrize("kind", ["pose2", "pose3"])
def test_gauss_newton_reaches_levenberg_marquardt_error(kind):
    rng = np.random.default_rng(13)
    n = 40
    g, truth = gtsam.NonlinearFactorGraph(), []
    d = 3 if kind == "pose2" else 6
    for i in range(n):  # a noisy loop
        a = 2 * np.pi * i / n
        if d == 3:
            truth.append(gtsam.Pose2(5 * np.cos(a), 5 * np.sin(a), a + np.pi / 2))
        else:
            truth.append(gtsam.Pose3(gtsam.Rot3.Ypr(a + np.pi / 2, 0.1 * np.sin(3 * a), 0.0),
                                     np.array([5 * np.cos(a), 5 * np.sin(a), np.sin(2 * a)])))
    sig = np.r_[0.05, 0.05, 0.02] if d == 3 else np.r_[0.02, 0.02, 0.02, 0.05, 0.05, 0.05]
    nm = N.Diagonal.Sigmas(sig)
    Between = gtsam.BetweenFactorPose2 if d == 3 else gtsam.BetweenFactorPose3
    cls = gtsam.Pose2 if d == 3 else gtsam.Pose3
    noisy = lambda p: p.compose(cls.Expmap(rng.normal(size=d) * sig))  # noqa: E731
    g.add((gtsam.PriorFactorPose2 if d == 3 else gtsam.PriorFactorPose3)(0, truth[0], N.Isotropic.Sigma(d, 1e-3)))
    for i in range(n):
        j = (i + 1) % n
        g.add(Between(i, j, noisy(truth[i].between(truth[j])), nm))
    for i in range(0, n, 7):
        j = (i + n // 2) % n
        g.add(Between(i, j, noisy(truth[i].between(truth[j])), N.Robust.Create(M.Huber.Create(1.345), nm)))
    init = gtsam.Values()
    for i in range(n):
        init.insert(i, noisy(noisy(truth[i])))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-15)
    params.setAbsoluteErrorTol(1e-15)
    params.setMaxIterations(100)
    ref = gtsam.LevenbergMarquardtOptimizer(g, init, params).optimize()
    lin = NativeLinearizer(g, init)
    st = _gauss_newton(lin, lin.state(init))
    assert lin.error(st) == pytest.approx(g.error(ref), rel=1e-8)
    assert g.error(lin.values(st)) == pytest.approx(lin.error(st), rel=1e-12)


# ---------------------------------------------------------------------------------------------
# public datasets
# ---------------------------------------------------------------------------------------------

def _dataset_graph(name, is3d):
    graph, values = gtsam.readG2o(str(DATASETS / name), is3d)
    k0 = min(values.keys())
    if is3d:
        graph.add(gtsam.PriorFactorPose3(k0, values.atPose3(k0), N.Isotropic.Sigma(6, 1e-3)))
    else:
        graph.add(gtsam.PriorFactorPose2(k0, values.atPose2(k0), N.Isotropic.Sigma(3, 1e-3)))
    return graph, values


def _gtsam_sparse_system(graph, values, offsets):
    """H = JᵀJ, g = −Jᵀb from ``sparseJacobian_`` (the package's export path)."""
    n = int(offsets[-1])
    S = graph.linearize(values).sparseJacobian_()
    r, c, x = S[0].astype(np.int64) - 1, S[1].astype(np.int64) - 1, S[2]
    rhs = c == n
    m = int(r.max()) + 1
    J = sp.csr_matrix((x[~rhs], (r[~rhs], c[~rhs])), shape=(m, n))
    b = np.bincount(r[rhs], x[rhs], minlength=m)
    return (J.T @ J).tocsr(), -(J.T @ b)


@pytest.mark.skipif(not (DATASETS / "input_M3500_g2o.g2o").exists(), reason=f"dataset folder {DATASETS} absent")
@pytest.mark.parametrize("name,is3d", [("input_M3500_g2o.g2o", False), ("sphere2500.g2o", True)])
def test_public_datasets(name, is3d):
    """Error = graph.error; H, g = GTSAM's sparse export to 1e-9 once the factors with
    1e-10 < |w| < 1e-3 are left out (GTSAM's Pose2 Jacobian/Logmap cancel there; M3500 has 946)."""
    graph, values = _dataset_graph(name, is3d)
    lin = NativeLinearizer(graph, values)
    assert lin.gtsam_factor_count == 0
    st = lin.state(values)
    assert lin.error(st) == pytest.approx(graph.error(values), rel=1e-12)
    if not is3d:
        keep = gtsam.NonlinearFactorGraph()
        for k in range(graph.size()):
            f = graph.at(k)
            w = abs(f.unwhitenedError(values)[2])
            if not 1e-10 < w < 1e-3:
                keep.add(f)
        graph = keep
        lin = NativeLinearizer(graph, values)
        st = lin.state(values)
    system = lin.linearize(st)
    H, g = _gtsam_sparse_system(graph, values, lin.offsets)
    assert abs(system.H - H).max() < 1e-9 * abs(H).max()
    assert np.linalg.norm(system.g - g) < 1e-9 * np.linalg.norm(g)
    assert system.error == pytest.approx(graph.error(values), rel=1e-12)


@pytest.mark.parametrize("kind", ["pose2", "pose3"])
def test_gauge_check_on_native_hessians(kind):
    """free_components on native H: a component without a prior is anchored at its first pose, one
    with a prior is not (two disjoint copies of a loop, with and without priors)."""
    from gtsam_schwarz.nonlinear.gauge import free_components

    rng = np.random.default_rng(12)
    g1, v1 = pose_graph(kind, 12, "diagonal", rng)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values(v1)
    for k in range(g1.size()):
        f = g1.at(k)
        graph.add(f)
        keys = [X(gtsam.Symbol(key).index() + 100) for key in f.keys()]   # the copy: the same factor, shifted
        if len(keys) == 2:
            graph.add(type(f)(keys[0], keys[1], f.measured(), f.noiseModel()))
    for key in v1.keys():
        p = v1.atPose2(key) if kind == "pose2" else v1.atPose3(key)
        values.insert(X(gtsam.Symbol(key).index() + 100), p)
    lin = NativeLinearizer(graph, values)
    st = lin.state(values)
    H = lin.linearize(st).H
    free = free_components(H, lin.offsets, lin.geometry(st))
    assert lin.keys[free].tolist() == [X(100)]   # the copy has no prior; the original has one
    # the prior's rows of Hz alone: the same anchors
    assert lin.keys[lin.prior_vertices].tolist() == [X(0)]
    assert np.array_equal(free_components(H, lin.offsets, lin.geometry(st), sources=lin.prior_vertices), free)
    bare = gtsam.NonlinearFactorGraph()
    for k in range(graph.size()):
        if len(graph.at(k).keys()) == 2:
            bare.add(graph.at(k))
    lin = NativeLinearizer(bare, values)
    st = lin.state(values)
    H = lin.linearize(st).H
    free = free_components(H, lin.offsets, lin.geometry(st))
    assert lin.keys[free].tolist() == [X(0), X(100)]
    # between factors only: every component free without the test on H's numbers, the same anchors
    assert len(lin.prior_vertices) == 0
    assert np.array_equal(free_components(H, lin.offsets, lin.geometry(st), sources=lin.prior_vertices), free)


def test_diagonal_sums_in_groups_equal_one_group(monkeypatch):
    """2D diagonal contributions are summed per pose a group of chunks at a time (a bounded scratch of
    about max(n, 2^18) columns): groups of a few chunks give H, g and the error of a single group to
    rounding (a lawnmower whose 67 081 factor ends fill five groups of 2 chunks + 1 000 columns)."""
    import gtsam_schwarz.linearization.native as native
    from gtsam_schwarz.problems import lawnmower
    assert native._group_width(1000, 10**7) == (1 << 18) + 2 * nk.CHUNK
    assert native._group_width(10**6, 10**7) == 10**6 + 2 * nk.CHUNK and native._group_width(10**6, 5000) == 5000
    prob = lawnmower(130, 130, sigma=0.01, seed=0)
    ends = 2 * (130 * 130 - 1 + 129 * 129) + 1
    runs = {}
    for width in (2 * nk.CHUNK + 1000, ends):
        monkeypatch.setattr(native, "_group_width", lambda n, columns, w=width: min(columns, w))
        lin = NativeLinearizer.from_arrays(**prob.arrays)
        runs[width] = lin.linearize(lin.state(prob.initial))
        assert lin._buffers["C3"].shape[1] == width
    a, b = runs.values()
    np.testing.assert_allclose(a.H.data, b.H.data, rtol=1e-13, atol=1e-12 * np.abs(b.H.data).max())
    np.testing.assert_allclose(a.g, b.g, rtol=1e-13, atol=1e-12 * np.abs(b.g).max())
    assert a.error == pytest.approx(b.error, rel=1e-14)


def test_released_start_poses_are_refused_with_a_clear_error():
    """release_initial drops the poses given to from_arrays; a solve from other values is unchanged, and
    asking for the released start says so instead of failing on a missing array."""
    from gtsam_schwarz.problems import lawnmower
    prob = lawnmower(12, 12, sigma=0.01, seed=0)
    kept = NativeLinearizer.from_arrays(**prob.arrays)
    released = NativeLinearizer.from_arrays(**prob.arrays)
    released.release_initial()
    a = kept.linearize(kept.state(prob.initial))
    b = released.linearize(released.state(prob.initial))
    np.testing.assert_array_equal(a.H.data, b.H.data)
    assert kept.initial_state() is not None
    with pytest.raises(RuntimeError, match="released"):
        released.initial_state()


def test_held_index_arrays_are_32_bit_where_they_fit():
    """H's diagonal positions and the diagonal contributions' poses are held through a solve: 32 bits
    where the numbers fit (1M 2D poses: 27 MiB less), and H the same as with 64-bit ones."""
    from gtsam_schwarz.problems import lawnmower
    prob = lawnmower(20, 20, sigma=0.01, seed=1)
    lin = NativeLinearizer.from_arrays(**prob.arrays)
    system = lin.linearize(lin.state(prob.initial))
    assert lin.diagonal.dtype == np.int32 and lin._k2.cidx.dtype == np.int32
    rows = np.repeat(np.arange(system.H.shape[0]), np.diff(system.H.indptr))
    np.testing.assert_array_equal(lin.diagonal, np.flatnonzero(rows == system.H.indices))
    np.testing.assert_array_equal(system.H.diagonal(), system.H.data[lin.diagonal])
    dense = system.H.toarray()
    np.testing.assert_allclose(dense, dense.T, rtol=0, atol=1e-12 * np.abs(dense).max())
