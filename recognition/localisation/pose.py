"""Pose of the sensor from mixed scene-model correspondences (closed form, weighted refinement, covariance).

A correspondence pairs a primitive fitted in the **sensor** frame with an a priori model feature in the
**world** frame; the unknown is ``T_world_sensor = (R, t)`` with ``p_world = R p_sensor + t``. Three kinds:

* :class:`PlanePair` - scene plane (unit normal facing the sensor, a point on it: the patch centroid) and
  model plane ``n_m . x = d_m`` (outward normal): 2 rotation + 1 translation constraints.
* :class:`AxisPair` - scene axis line (point, direction) and model axis line (cylinders, cones); the sign
  of the direction is ambiguous for cylinders (``signed=False``) and known for cones. An optional
  ``along_m`` fixes the position along the axis (cones: where the model radius equals the fitted radius).
  2 rotation + 2 translation constraints (+1 with ``along_m``).
* :class:`PointPair` - a scene point and a model point (sphere centres): 3 translation constraints (and
  rotation constraints once there are two of them).

:func:`estimate_pose` solves the rotation in closed form (weighted Kabsch/Horn over the direction pairs:
plane normals, axes under every sign assignment, and directions derived between pairs - the perpendicular
between two parallel axes, from an axis to a point, between two points - which fix the roll that one
family of parallel directions leaves), then the translation by linear least squares, then refines both by
Gauss-Newton on all whitened residuals. The covariance ``cov_T_world_sensor`` (6, 6) is over the rotation
vector (rad) and translation (m) of a **left** perturbation in the world frame,
``T = exp([w, v]^) T_hat`` (DESIGN 10.11), i.e. ``(J' J)^+`` of the whitened residuals. The number of
degrees of freedom the pairs leave unconstrained is reported (never hidden): one cylinder leaves 2, three
non-parallel plane normals or two non-parallel axes constrain all 6.

All functions are pure and deterministic; a degenerate input is a result with ``ok=False`` and a reason.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from scenes.geometry import perpendicular_basis

__all__ = [
    "PlanePair",
    "AxisPair",
    "PointPair",
    "Pair",
    "PoseEstimate",
    "estimate_pose",
    "pose_hypotheses",
    "residuals",
    "skew",
    "exp_so3",
    "log_so3",
    "apply_left",
    "free_dof_of",
]


@dataclass(frozen=True)
class PlanePair:
    """Scene plane (sensor frame) <-> model plane (world frame).

    Attributes
    ----------
    n_s : ndarray of shape (3,), unit normal in the sensor frame (same side as ``n_m``: facing the sensor).
    c_s : ndarray of shape (3,), metres, a point of the scene plane (the patch centroid).
    n_m : ndarray of shape (3,), unit outward normal of the model plane (world).
    d_m : float, metres, model plane offset ``n_m . x = d_m``.
    sigma_angle : float, radians, per-component sigma of the normal.
    sigma_offset : float, metres, sigma of the plane position at ``c_s``.
    """

    n_s: np.ndarray
    c_s: np.ndarray
    n_m: np.ndarray
    d_m: float
    sigma_angle: float
    sigma_offset: float


@dataclass(frozen=True)
class AxisPair:
    """Scene axis line (sensor frame) <-> model axis line (world frame).

    Attributes
    ----------
    a_s, p_s : ndarray of shape (3,), scene axis direction (unit) and a point of it (metres).
    a_m, p_m : ndarray of shape (3,), model axis direction (unit) and a point of it (metres).
    sigma_angle : float, radians, per-component sigma of the axis direction.
    sigma_pos : float, metres, per-component sigma of the line position (across the axis).
    signed : bool
        True when ``R a_s`` must equal ``+a_m`` (cones); False when the sign is unknown (cylinders).
    along_m : float or None, metres
        When given, ``a_m . (R p_s + t - p_m) = along_m`` (position along the axis, for cones).
    sigma_along : float, metres, sigma of that constraint.
    """

    a_s: np.ndarray
    p_s: np.ndarray
    a_m: np.ndarray
    p_m: np.ndarray
    sigma_angle: float
    sigma_pos: float
    signed: bool = False
    along_m: float | None = None
    sigma_along: float = np.inf


@dataclass(frozen=True)
class PointPair:
    """Scene point (sensor frame) <-> model point (world frame), e.g. sphere centres.

    Attributes
    ----------
    c_s, c_m : ndarray of shape (3,), metres.
    sigma : float, metres, per-component sigma.
    """

    c_s: np.ndarray
    c_m: np.ndarray
    sigma: float


Pair = PlanePair | AxisPair | PointPair


@dataclass(frozen=True)
class PoseEstimate:
    """Result of :func:`estimate_pose`.

    Attributes
    ----------
    ok : bool
    reason : str, why not ok ("" otherwise).
    T_world_sensor : ndarray of shape (4, 4) or None
    cov_T_world_sensor : ndarray of shape (6, 6) or None
        Over (rotation vector rad, translation m), left perturbation in the world frame; the pseudo-inverse
        of the information, so free directions carry zero variance: read ``free_dof`` and ``free_basis``.
    free_dof : int, 0..6, degrees of freedom the pairs leave unconstrained.
    free_basis : ndarray of shape (6, free_dof), the unconstrained directions (rad, m).
    cost : float, sum of squared whitened residuals at the estimate.
    signs : tuple[int, ...], the chosen sign (+1/-1) of each pair (always +1 for non-axis pairs).
    n_residuals : int
    """

    ok: bool
    reason: str
    T_world_sensor: np.ndarray | None
    cov_T_world_sensor: np.ndarray | None
    free_dof: int
    free_basis: np.ndarray
    cost: float
    signs: tuple[int, ...]
    n_residuals: int

    def __bool__(self) -> bool:
        return self.ok


# ---------------------------------------------------------------------------------------------------------
# SO(3) helpers


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix ``[v]x`` (3, 3) with ``[v]x u = v x u``."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def exp_so3(w: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of the rotation vector ``w`` (3,), radians (Rodrigues)."""
    w = np.asarray(w, dtype=np.float64)
    th = float(np.sqrt(w @ w))
    K = skew(w)
    if th < 1e-8:
        return np.eye(3) + K + 0.5 * K @ K
    return np.eye(3) + np.sin(th) / th * K + (1.0 - np.cos(th)) / th**2 * K @ K


def log_so3(R: np.ndarray) -> np.ndarray:
    """Rotation vector (3,) of a rotation matrix (3, 3), radians."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_rotvec()


def apply_left(T: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """``exp([w, v]^) T`` for ``delta = (w, v)`` (6,), a left (world-frame) perturbation of ``T`` (4, 4).

    First order in ``v``: the point ``p`` maps to ``exp(w) p + v`` (the convention of the covariance).
    """
    dR = exp_so3(delta[:3])
    out = np.eye(4)
    out[:3, :3] = dR @ T[:3, :3]
    out[:3, 3] = dR @ T[:3, 3] + delta[3:]
    return out


# ---------------------------------------------------------------------------------------------------------
# residuals


def _rows(pairs, signs) -> tuple[np.ndarray, ...]:
    """Every residual is one of two row forms (so all are evaluated at once on arrays):

    * direction rows ``e . (R d) / sigma`` (``e`` across the model direction, ``d`` the signed scene one);
    * position rows ``(e . (R q + t) - b) / sigma``.

    Returns ``(Ed, Dd, sd, Ep, Qp, bp, sp)``: arrays of shapes (Nd, 3), (Nd, 3), (Nd,), (Np, 3), (Np, 3),
    (Np,), (Np,).
    """
    Ed, Dd, sd, Ep, Qp, bp, sp = [], [], [], [], [], [], []
    for pair, s in zip(pairs, signs, strict=True):
        if isinstance(pair, PlanePair):
            for e in perpendicular_basis(pair.n_m):
                Ed.append(e)
                Dd.append(pair.n_s)
                sd.append(pair.sigma_angle)
            Ep.append(pair.n_m)
            Qp.append(pair.c_s)
            bp.append(pair.d_m)
            sp.append(pair.sigma_offset)
        elif isinstance(pair, AxisPair):
            for e in perpendicular_basis(pair.a_m):
                Ed.append(e)
                Dd.append(s * pair.a_s)
                sd.append(pair.sigma_angle)
                Ep.append(e)
                Qp.append(pair.p_s)
                bp.append(float(e @ pair.p_m))
                sp.append(pair.sigma_pos)
            if pair.along_m is not None:
                Ep.append(pair.a_m)
                Qp.append(pair.p_s)
                bp.append(float(pair.a_m @ pair.p_m) + pair.along_m)
                sp.append(pair.sigma_along)
        else:
            for k in range(3):
                Ep.append(np.eye(3)[k])
                Qp.append(pair.c_s)
                bp.append(float(pair.c_m[k]))
                sp.append(pair.sigma)

    def arr(x, shape):
        return np.array(x, dtype=np.float64).reshape(shape)

    return (arr(Ed, (-1, 3)), arr(Dd, (-1, 3)), arr(sd, (-1,)), arr(Ep, (-1, 3)), arr(Qp, (-1, 3)),
            arr(bp, (-1,)), arr(sp, (-1,)))


def _cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    out = np.empty_like(a)
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def _eval_rows(rows, T: np.ndarray, jacobian: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    Ed, Dd, sd, Ep, Qp, bp, sp = rows
    R, t = T[:3, :3], T[:3, 3]
    d = Dd @ R.T
    p = Qp @ R.T + t
    r = np.concatenate([np.sum(Ed * d, axis=1) / sd, (np.sum(Ep * p, axis=1) - bp) / sp])
    if not jacobian:
        return r, None
    J = np.zeros((len(r), 6))
    nd = len(sd)
    J[:nd, :3] = _cross_rows(d, Ed) / sd[:, None]
    J[nd:, :3] = _cross_rows(p, Ep) / sp[:, None]
    J[nd:, 3:] = Ep / sp[:, None]
    return r, J


def residuals(pairs: tuple[Pair, ...] | list[Pair], signs: tuple[int, ...], T: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
    """Whitened residuals (M,) and their Jacobian (M, 6) w.r.t. a left perturbation ``(w, v)`` of ``T``.

    Plane: the two components of ``R n_s`` across ``n_m`` and the distance of ``R c_s + t`` to the model
    plane. Axis: the two components of ``s R a_s`` across ``a_m``, the two components of ``R p_s + t - p_m``
    across ``a_m`` (and along it minus ``along_m`` when given). Point: ``R c_s + t - c_m``. Direction rows
    come first, then position rows.
    """
    return _eval_rows(_rows(pairs, signs), np.asarray(T, dtype=np.float64))


def free_dof_of(J: np.ndarray, length_m: float = 1.0, max_sigma: float = 0.1) -> tuple[int, np.ndarray]:
    """Unconstrained directions of the information ``J' J`` (J: whitened, (M, 6)).

    The translation columns are scaled by ``length_m`` (a characteristic scene length) so both blocks are
    comparable; a direction is free when its standard deviation exceeds ``max_sigma`` (rad, or
    ``length_m`` units) or its eigenvalue is numerically zero (< 1e-10 of the largest).

    Returns
    -------
    (free_dof, basis) : int and ndarray of shape (6, free_dof) (unit vectors in the scaled space).
    """
    S = np.diag([1.0, 1.0, 1.0, length_m, length_m, length_m])
    info = S @ (J.T @ J) @ S
    vals, vecs = np.linalg.eigh(info)
    top = max(float(vals[-1]), 1e-300)
    free = (vals < 1e-10 * top) | (vals < 1.0 / max_sigma**2)
    basis = S @ vecs[:, free]
    norms = np.linalg.norm(basis, axis=0)
    return int(free.sum()), basis / np.where(norms > 0, norms, 1.0)


# ---------------------------------------------------------------------------------------------------------
# closed form


def _kabsch(src: np.ndarray, dst: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Rotation R maximising ``sum w_i dst_i . (R src_i)`` (directions (K, 3), weights (K,))."""
    B = (dst * w[:, None]).T @ src
    U, _, Vt = np.linalg.svd(B)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    return U @ D @ Vt


def _directions(pairs, signs) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Direction correspondences (scene (K, 3), model (K, 3), weights (K,)) for the rotation."""
    src, dst, w = [], [], []
    lines = []  # (a_s, p_s, a_m, p_m, sigma_pos)
    pts = []  # (c_s, c_m, sigma)
    for pair, s in zip(pairs, signs, strict=True):
        if isinstance(pair, PlanePair):
            src.append(pair.n_s)
            dst.append(pair.n_m)
            w.append(1.0 / pair.sigma_angle**2)
        elif isinstance(pair, AxisPair):
            src.append(s * pair.a_s)
            dst.append(pair.a_m)
            w.append(1.0 / pair.sigma_angle**2)
            lines.append((pair.a_s, pair.p_s, pair.a_m, pair.p_m, pair.sigma_pos))
            if pair.along_m is not None and np.isfinite(pair.sigma_along):
                pts.append((pair.p_s, pair.p_m + pair.along_m * pair.a_m,
                            float(np.hypot(pair.sigma_pos, pair.sigma_along))))
        else:
            pts.append((pair.c_s, pair.c_m, pair.sigma))
    # derived directions: parallel lines (perpendicular between them), line -> point, point -> point
    for (a1s, p1s, a1m, p1m, s1), (a2s, p2s, a2m, p2m, s2) in itertools.combinations(lines, 2):
        if abs(a1s @ a2s) > 0.995 and abs(a1m @ a2m) > 0.995:
            ds = (p2s - p1s) - ((p2s - p1s) @ a1s) * a1s
            dm = (p2m - p1m) - ((p2m - p1m) @ a1m) * a1m
            ls, lm = np.linalg.norm(ds), np.linalg.norm(dm)
            if ls > 10 * np.hypot(s1, s2) and lm > 1e-9:
                src.append(ds / ls)
                dst.append(dm / lm)
                w.append(ls**2 / (s1**2 + s2**2))
    for (a_s, p_s, a_m, p_m, s1), (c_s, c_m, s2) in itertools.product(lines, pts):
        ds = (c_s - p_s) - ((c_s - p_s) @ a_s) * a_s
        dm = (c_m - p_m) - ((c_m - p_m) @ a_m) * a_m
        ls, lm = np.linalg.norm(ds), np.linalg.norm(dm)
        if ls > 10 * np.hypot(s1, s2) and lm > 1e-9:
            src.append(ds / ls)
            dst.append(dm / lm)
            w.append(ls**2 / (s1**2 + s2**2))
    for (c1s, c1m, s1), (c2s, c2m, s2) in itertools.combinations(pts, 2):
        ds, dm = c2s - c1s, c2m - c1m
        ls, lm = np.linalg.norm(ds), np.linalg.norm(dm)
        if ls > 10 * np.hypot(s1, s2) and lm > 1e-9:
            src.append(ds / ls)
            dst.append(dm / lm)
            w.append(ls**2 / (s1**2 + s2**2))
    if not src:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)
    return np.array(src), np.array(dst), np.array(w)


def _translation(rows, R: np.ndarray) -> np.ndarray:
    """Weighted linear least-squares translation (3,) given R (minimum-norm in free directions)."""
    _, _, _, Ep, Qp, bp, sp = rows
    A = Ep / sp[:, None]
    b = (bp - np.sum(Ep * (Qp @ R.T), axis=1)) / sp
    t, *_ = np.linalg.lstsq(A, b, rcond=1e-10)
    return t


def _refine(rows, T: np.ndarray, iterations: int, jacobian: bool = True
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Gauss-Newton on the whitened residuals (minimum-norm steps in free directions); the Jacobian at the
    result is left out (None) for 0 iterations without ``jacobian``."""
    r, J = _eval_rows(rows, T, jacobian or iterations > 0)
    cost = float(r @ r)
    for _ in range(iterations):
        step, *_ = np.linalg.lstsq(J, -r, rcond=1e-10)
        T_new = apply_left(T, step)
        r_new, J_new = _eval_rows(rows, T_new)
        c_new = float(r_new @ r_new)
        if not c_new <= cost:
            break
        done = cost - c_new <= 1e-12 * max(cost, 1e-300) or float(step @ step) < 1e-24
        T, r, J, cost = T_new, r_new, J_new, c_new
        if done:
            break
    return T, r, J


def _sign_sets(pairs, min_cos: float = 0.2, max_sets: int = 64) -> list[tuple[int, ...]]:
    """Sign assignments of the unsigned axes that agree with the signs the pairs imply among themselves.

    Rotations preserve dot products, so for two directions with ``|a_s . b_s| >= min_cos`` the product of
    their signs must equal ``sign(a_m . b_m) / sign(a_s . b_s)`` (plane normals and cone axes have sign +1).
    """
    dirs = []
    for p in pairs:
        if isinstance(p, PlanePair):
            dirs.append((p.n_s, p.n_m))
        elif isinstance(p, AxisPair):
            dirs.append((p.a_s, p.a_m))
        else:
            dirs.append(None)
    unsigned = {i for i, p in enumerate(pairs) if isinstance(p, AxisPair) and not p.signed}
    # parity graph: an edge (j, rel) says sign_i * sign_j must equal rel
    adj: dict[int, list[tuple[int, int]]] = {i: [] for i in range(len(pairs))}
    for i, j in itertools.combinations(range(len(pairs)), 2):
        if dirs[i] is None or dirs[j] is None or (i not in unsigned and j not in unsigned):
            continue
        cs, cm = float(dirs[i][0] @ dirs[j][0]), float(dirs[i][1] @ dirs[j][1])
        if abs(cs) >= min_cos and abs(cm) >= min_cos:
            rel = 1 if cs * cm > 0 else -1
            adj[i].append((j, rel))
            adj[j].append((i, rel))
    # connected components by breadth-first propagation (linear, not 2^n): a component holding a signed
    # direction is fixed; every other component has two sign choices (all of its members flip together)
    sign = [1] * len(pairs)
    seen: set[int] = set()
    free_components: list[list[int]] = []
    for root in sorted(range(len(pairs)), key=lambda k: k in unsigned):  # signed roots first
        if root in seen:
            continue
        seen.add(root)
        comp, queue = [root], [root]
        while queue:
            k = queue.pop()
            for j, rel in adj[k]:
                if j not in seen and j in unsigned:  # signed directions keep +1 (each is a root of its own)
                    seen.add(j)
                    sign[j] = sign[k] * rel
                    comp.append(j)
                    queue.append(j)
        if root in unsigned and all(k in unsigned for k in comp):
            free_components.append(comp)
    out = []
    for combo in itertools.product((1, -1), repeat=len(free_components)):
        s = list(sign)
        for comp, v in zip(free_components, combo, strict=True):
            for k in comp:
                s[k] = sign[k] * v
        out.append(tuple(s))
        if len(out) >= max_sets:
            break
    return out or [tuple(sign)]


def pose_hypotheses(pairs: tuple[Pair, ...] | list[Pair], *, iterations: int = 5, length_m: float = 1.0,
                    max_sigma: float = 0.1, max_signs: int = 64, T_init: np.ndarray | None = None,
                    assess: bool = True) -> list[PoseEstimate]:
    """Every pose the pairs allow under the sign assignments of their unsigned axes, best first.

    Parameters
    ----------
    pairs : sequence of :class:`PlanePair`, :class:`AxisPair`, :class:`PointPair`.
    iterations : Gauss-Newton iterations after the closed form.
    length_m : characteristic scene length (metres) for the free-DOF test (:func:`free_dof_of`).
    max_sigma : sigma (rad, or ``length_m`` units) above which a direction counts as free.
    max_signs : at most this many sign assignments are tried (the first unsigned axes vary first).
    T_init : optional (4, 4) pose used to pick, for each unsigned axis, the sign it implies, and to fill
        the free directions (the rotation about a single axis, a translation along it) instead of the
        minimum-norm choice.
    assess : when False (a quick pose inside a search), the free DOF and the covariance are not computed:
        ``free_dof`` is reported as 0 and ``cov_T_world_sensor`` as None.

    Returns
    -------
    list of PoseEstimate, sorted by cost (empty or a single ``ok=False`` entry when degenerate).
    """
    pairs = tuple(pairs)
    if not pairs:
        return [_fail("no correspondences", 0)]
    if T_init is not None:
        R0 = T_init[:3, :3]
        signs = tuple(int(np.sign(p.a_m @ (R0 @ p.a_s)) or 1) if isinstance(p, AxisPair) and not p.signed else 1
                      for p in pairs)
        sign_sets = [signs]
    else:
        sign_sets = _sign_sets(pairs, max_sets=max_signs)
    out: list[PoseEstimate] = []
    for signs in sign_sets:
        src, dst, w = _directions(pairs, signs)
        if T_init is not None:
            # anchor the rotation to T_init in directions the pairs do not fix (tiny weight)
            R0 = T_init[:3, :3]
            eye = np.eye(3)
            src = np.vstack([src, eye]) if len(src) else eye
            dst = np.vstack([dst, (R0 @ eye).T]) if len(dst) else (R0 @ eye).T
            w = np.concatenate([w, np.full(3, 1e-9 * (w.max() if len(w) else 1.0))])
        if len(src) == 0:
            R = np.eye(3)
        else:
            R = _kabsch(src, dst, w)
        rows = _rows(pairs, signs)
        t = _translation(rows, R)
        if T_init is not None:
            # replace the minimum-norm translation's free part by T_init's
            Jt = rows[3] / rows[6][:, None]
            _, sv, Vt = np.linalg.svd(Jt, full_matrices=True)
            rank = int(np.sum(sv > 1e-10 * max(sv.max(initial=0.0), 1e-300)))
            N = Vt[rank:].T
            t = t + N @ (N.T @ (T_init[:3, 3] - t))
        T = _make_T(R, t)
        T, r, J = _refine(rows, T, iterations, jacobian=assess)
        if not assess:
            out.append(PoseEstimate(True, "", T, None, 0, np.zeros((6, 0)), float(r @ r), signs, len(r)))
            continue
        free, basis = free_dof_of(J, length_m, max_sigma)
        info = J.T @ J
        cov = np.linalg.pinv(info, rcond=1e-12, hermitian=True)
        out.append(PoseEstimate(True, "", T, cov, free, basis, float(r @ r), signs, len(r)))
    return sorted_with_ties(out, cost=lambda e: e.cost, tiebreak=lambda e: e.signs)


#: two whitened costs within this fraction of each other are the same fit up to rounding
COST_TIE_REL = 1e-9


def sorted_with_ties(items: list, cost, tiebreak, first=lambda x: ()) -> list:
    """``items`` sorted by ``(first(x), cost(x))`` with a tie rule: within one ``first`` key, costs within
    :data:`COST_TIE_REL` of the first of their run (the two signs of a symmetric pair of pipes, the mirror
    interpretations of a symmetric bay: the same fit up to rounding) are ordered by ``tiebreak(x)``, so that
    which one comes first does not turn on the last bits of the fits (``python -m harness.bench.stability``)."""
    ranked = sorted(items, key=lambda x: (first(x), cost(x)))
    out: list = []
    k = 0
    while k < len(ranked):
        j = k + 1
        c0 = cost(ranked[k])
        while j < len(ranked) and first(ranked[j]) == first(ranked[k]) and \
                cost(ranked[j]) <= c0 + COST_TIE_REL * max(abs(c0), 1e-12):
            j += 1
        out.extend(sorted(ranked[k:j], key=tiebreak))
        k = j
    return out


def estimate_pose(pairs: tuple[Pair, ...] | list[Pair], **kwargs) -> PoseEstimate:
    """The best pose (lowest whitened cost) from the pairs; see :func:`pose_hypotheses` for the arguments.

    Examples
    --------
    >>> n = np.eye(3)
    >>> pairs = [PlanePair(n[i], n[i] * 2.0, n[i], 2.0, 1e-3, 1e-3) for i in range(3)]
    >>> est = estimate_pose(pairs)
    >>> bool(np.allclose(est.T_world_sensor, np.eye(4))), est.free_dof
    (True, 0)
    """
    hyps = pose_hypotheses(pairs, **kwargs)
    return hyps[0]


def _make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _fail(reason: str, n: int) -> PoseEstimate:
    return PoseEstimate(False, reason, None, None, 6, np.eye(6), np.inf, (1,) * n, 0)
