"""Secondary rays spawned at hit points: diffuse bounces, shadow rays, ambient occlusion.

These are the incoherent ray sets of the benchmark protocol (tinybvh's speed test,
STYLE §11): after tracing a batch, every ray that hit spawns new rays from its hit
point. Each generator returns the new :class:`~rayaccel.rays.batch.RayBatch` and an
int32 ``source`` array giving, for every new ray, the index of the ray it came
from, so results can be scattered back to pixels.

Directions are sampled around the **geometric normal** ``normals[prim]`` of the hit
triangle, flipped to face the incoming ray. Cosine-weighted hemisphere directions
use Malley's method: sample the unit disk uniformly with Shirley and Chiu's
concentric mapping and project up onto the hemisphere (Pharr, Jakob & Humphreys,
*Physically Based Rendering*, 3rd ed. §13.6.2-13.6.3, 4th ed. §A.5.3); the local
frame around the normal is Duff et al. (2017), "Building an Orthonormal Basis,
Revisited", JCGT 6(1). Area lights are sampled uniformly by area, then uniformly
inside the triangle with ``b0 = 1 - sqrt(u1)``, ``b1 = u2·sqrt(u1)`` (PBR 3rd ed.
§13.6.5).

**Self-intersection.** A hit point computed in float32 lies up to a few ulps off
the surface, so a new ray leaving it may hit its own triangle at ``t ≈ 0``. Every
generator offsets the origin along the normal, to the side the new ray leaves
towards, by ``epsilon · scale`` with ``scale = max(1, |p|∞, |o|∞, t·|d|∞)`` (the
hit point ``p`` and the incoming ray's origin ``o``, direction ``d`` and hit
distance ``t``, which bound the rounding error of ``p = o + t·d``), as pbrt's
``OffsetRayOrigin`` does with its error bounds; ``tmin`` is then 0. With the
default ``epsilon = 1e-4`` the offset is about 1700 float32 ulps of ``scale``.

Determinism: all randomness comes from ``numpy.random.Generator(PCG64(seed))``,
drawn in one block in the order of the source rays, so the output depends only on
the inputs and ``seed``. Rays that missed, whose triangle has a zero (degenerate)
normal, or whose hit point is not finite spawn nothing.

Cost: O(n) vectorised numpy in float64, a fraction of a second per million rays.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from rayaccel.dtypes import INDEX, REAL, FloatArray, IntArray
from rayaccel.errors import InvalidInputError
from rayaccel.rays.batch import HitBatch, RayBatch

F64Array = npt.NDArray[np.float64]

#: ``tmax`` of shadow rays, whose direction spans origin → light point: the ray stops
#: just before the light, so the light's own geometry never occludes it.
SHADOW_TMAX = 1.0 - 1e-4


def _check_epsilon(epsilon: object) -> float:
    try:
        value = float(epsilon)  # type: ignore[arg-type]
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"epsilon: expected a float, got {epsilon!r}") from exc
    if not (math.isfinite(value) and value >= 0.0):
        raise InvalidInputError(f"epsilon: expected a finite value >= 0, got {value}")
    return value


def _as_normals(normals: object) -> F64Array:
    try:
        array = np.asarray(normals, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"normals: expected an (F, 3) float array ({exc})") from exc
    if array.ndim != 2 or array.shape[1] != 3:
        raise InvalidInputError(f"normals: expected shape (F, 3), got {array.shape}")
    return array


def _rng(seed: object) -> np.random.Generator:
    try:
        return np.random.Generator(np.random.PCG64(seed))  # type: ignore[arg-type]
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"seed: expected a non-negative int, got {seed!r}") from exc


def _hit_frames(
    rays: RayBatch, hits: HitBatch, normals: object
) -> tuple[IntArray, F64Array, F64Array, F64Array]:
    """Gather the hits that can spawn rays.

    Returns
    -------
    source : (m,) int32
        Indices of the usable hits, ascending.
    points : (m, 3) float64
        Hit points ``o + t·d``.
    normals : (m, 3) float64
        Unit geometric normals, flipped to face the incoming ray.
    scale : (m,) float64
        Magnitude bounding the rounding error of each hit point (module docstring).
    """
    if not isinstance(rays, RayBatch):
        raise InvalidInputError(f"rays: expected a RayBatch, got {type(rays).__name__}")
    if not isinstance(hits, HitBatch):
        raise InvalidInputError(f"hits: expected a HitBatch, got {type(hits).__name__}")
    if len(hits) != rays.n_rays:
        raise InvalidInputError(f"hits: expected {rays.n_rays} hits to match rays, got {len(hits)}")
    table = _as_normals(normals)
    prim = np.asarray(hits.prim)
    source = np.flatnonzero(prim >= 0)
    prim = prim[source]
    if prim.size and int(prim.max()) >= table.shape[0]:
        raise InvalidInputError(
            f"hits: primitive {int(prim.max())} out of range for {table.shape[0]} normals"
        )
    normal = np.take(table, prim, axis=0)
    origin = np.take(rays.origin, source, axis=0).astype(np.float64)
    direction = np.take(rays.direction, source, axis=0).astype(np.float64)
    t = np.take(hits.t, source).astype(np.float64)
    points = origin + t[:, None] * direction
    # Degenerate triangles (zero normal) and non-finite hits spawn nothing
    length = np.sqrt(_dot(normal, normal))
    keep = (length > 0.0) & np.isfinite(length) & np.isfinite(_dot(points, points))
    if not keep.all():
        source, points, origin = source[keep], points[keep], origin[keep]
        direction, t, normal, length = direction[keep], t[keep], normal[keep], length[keep]
    normal /= length[:, None]
    # Face the incoming ray: the normal points against its direction
    normal *= np.where(_dot(normal, direction) > 0.0, -1.0, 1.0)[:, None]
    scale = np.maximum(
        np.maximum(1.0, _max_abs(points)),
        np.maximum(_max_abs(origin), t * _max_abs(direction)),
    )
    return source.astype(INDEX), points, normal, scale


def _dot(a: F64Array, b: F64Array) -> F64Array:
    """Row-wise dot product of two ``(m, 3)`` arrays."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def _max_abs(a: F64Array) -> F64Array:
    """Row-wise infinity norm of an ``(m, 3)`` array."""
    return np.maximum(np.maximum(np.abs(a[:, 0]), np.abs(a[:, 1])), np.abs(a[:, 2]))


def _offset(
    points: F64Array, normals: F64Array, directions: F64Array | None, amount: F64Array
) -> F64Array:
    if directions is None:
        return points + amount[:, None] * normals
    side = np.where(_dot(normals, directions) < 0.0, -1.0, 1.0)
    return points + (side * amount)[:, None] * normals


def offset_origin(
    points: npt.ArrayLike,
    normals: npt.ArrayLike,
    directions: npt.ArrayLike | None = None,
    *,
    epsilon: float = 1e-4,
    scale: npt.ArrayLike | None = None,
) -> FloatArray:
    """Push ray origins off a surface along its normal to avoid self-intersection.

    Parameters
    ----------
    points : (n, 3) array_like of float
        Points on the surface.
    normals : (n, 3) array_like of float
        Surface normals at ``points`` (normalised here; zero normals give no offset).
    directions : (n, 3) array_like of float, optional
        Directions of the rays to be spawned. When given, each point moves to the
        side of the surface its ray leaves towards (``-normal`` if
        ``dot(normal, direction) < 0``); otherwise it moves along ``+normal``.
    epsilon : float
        Relative offset, ``>= 0``. Default ``1e-4``.
    scale : float or (n,) array_like of float, optional
        Magnitude the offset is relative to. Default ``max(1, |p|∞)`` per point.

    Returns
    -------
    (n, 3) float32 ndarray
        ``points ± epsilon · scale · normal / |normal|``.

    Raises
    ------
    InvalidInputError
        On mismatched shapes or a negative or non-finite ``epsilon``.
    """
    eps = _check_epsilon(epsilon)
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise InvalidInputError(f"points: expected shape (n, 3), got {p.shape}")
    n = np.asarray(normals, dtype=np.float64)
    if n.shape != p.shape:
        raise InvalidInputError(f"normals: expected shape {p.shape}, got {n.shape}")
    length = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.divide(n, length, out=np.zeros_like(n), where=length > 0.0)
    d = None
    if directions is not None:
        d = np.asarray(directions, dtype=np.float64)
        if d.shape != p.shape:
            raise InvalidInputError(f"directions: expected shape {p.shape}, got {d.shape}")
    if scale is None:
        magnitude = np.maximum(1.0, np.abs(p).max(axis=1, initial=0.0))
    else:
        magnitude = np.broadcast_to(np.asarray(scale, dtype=np.float64), (p.shape[0],))
    return _offset(p, n, d, eps * magnitude).astype(REAL)


def cosine_hemisphere(normals: F64Array, u1: F64Array, u2: F64Array) -> F64Array:
    """Map uniform samples to cosine-weighted directions around unit normals.

    Parameters
    ----------
    normals : (m, 3) float64 ndarray
        Unit normals.
    u1, u2 : (m,) float64 ndarray
        Uniform samples in ``[0, 1)``.

    Returns
    -------
    (m, 3) float64 ndarray
        Unit directions with density ``cos θ / π`` about each normal, so
        ``E[cos θ] = 2/3``.

    Notes
    -----
    Malley's method: a uniform point on the unit disk (Shirley-Chiu concentric
    mapping, which keeps strata compact) lifted to ``z = sqrt(1 - x² - y²)``
    (PBR 3rd ed. §13.6.3). The tangent frame is Duff et al. (2017), continuous
    everywhere except at ``n_z = 0`` sign flips and free of normalisation.
    """
    # Concentric mapping of [0, 1)² onto the unit disk
    a = 2.0 * u1 - 1.0
    b = 2.0 * u2 - 1.0
    first = np.abs(a) > np.abs(b)
    radius = np.where(first, a, b)
    with np.errstate(divide="ignore", invalid="ignore"):
        phi = np.where(first, (np.pi / 4.0) * (b / a), (np.pi / 2.0) - (np.pi / 4.0) * (a / b))
    phi = np.where(radius == 0.0, 0.0, phi)
    x = radius * np.cos(phi)
    y = radius * np.sin(phi)
    z = np.sqrt(np.maximum(0.0, 1.0 - x * x - y * y))
    # Orthonormal basis around the normal (Duff et al. 2017, listing 3)
    nx, ny, nz = normals[:, 0], normals[:, 1], normals[:, 2]
    sign = np.where(nz >= 0.0, 1.0, -1.0)
    k = -1.0 / (sign + nz)
    m = nx * ny * k
    tangent = np.stack([1.0 + sign * nx * nx * k, sign * m, -sign * nx], axis=1)
    bitangent = np.stack([m, sign + ny * ny * k, -ny], axis=1)
    directions: F64Array = x[:, None] * tangent + y[:, None] * bitangent + z[:, None] * normals
    return directions


def diffuse_rays(
    rays: RayBatch,
    hits: HitBatch,
    normals: npt.ArrayLike,
    *,
    seed: int = 0,
    epsilon: float = 1e-4,
) -> tuple[RayBatch, IntArray]:
    """Spawn one cosine-weighted diffuse bounce per hit.

    Parameters
    ----------
    rays : RayBatch
        The traced rays, ``n`` of them.
    hits : HitBatch
        Their closest hits; rays with ``prim < 0`` spawn nothing.
    normals : (F, 3) array_like of float
        Geometric normal of every triangle (any length; zero marks a degenerate
        triangle, whose hits spawn nothing).
    seed : int
        Seed of the PCG64 generator.
    epsilon : float
        Relative origin offset along the normal (module docstring). Default 1e-4.

    Returns
    -------
    rays : RayBatch
        ``m <= n`` rays: origin at the offset hit point, a unit direction in the
        hemisphere of the normal facing the incoming ray, ``tmin = 0``,
        ``tmax = inf``.
    source : (m,) int32 ndarray
        Index in ``rays`` of the ray each new ray continues, ascending.

    Raises
    ------
    InvalidInputError
        On mismatched lengths, bad normals, a primitive index outside
        ``normals`` or a bad ``epsilon``/``seed``.
    """
    eps = _check_epsilon(epsilon)
    source, points, normal, scale = _hit_frames(rays, hits, normals)
    rng = _rng(seed)
    u = rng.random((len(source), 2))
    direction = cosine_hemisphere(normal, u[:, 0], u[:, 1])
    origin = _offset(points, normal, None, eps * scale)
    return RayBatch(origin.astype(REAL), direction.astype(REAL), 0.0, np.inf), source


def _light_points(light: object, count: int, rng: np.random.Generator) -> F64Array:
    try:
        array = np.asarray(light, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(
            f"light: expected a (3,) point or (k, 3, 3) triangles ({exc})"
        ) from exc
    if not np.isfinite(array).all():
        raise InvalidInputError("light: expected finite coordinates")
    if array.shape == (3,):
        return np.broadcast_to(array, (count, 3))
    if array.ndim != 3 or array.shape[1:] != (3, 3) or array.shape[0] == 0:
        raise InvalidInputError(
            f"light: expected a (3,) point or (k, 3, 3) triangles, got shape {array.shape}"
        )
    a, b, c = array[:, 0], array[:, 1], array[:, 2]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    total = float(area.sum())
    if not total > 0.0:
        raise InvalidInputError("light: all light triangles have zero area")
    # Pick a triangle with probability proportional to its area
    u = rng.random((count, 3))
    cdf = np.cumsum(area) / total
    tri = np.minimum(np.searchsorted(cdf, u[:, 0], side="right"), array.shape[0] - 1)
    # Uniform point inside it (PBR 3rd ed. §13.6.5)
    root = np.sqrt(u[:, 1])
    b0 = 1.0 - root
    b1 = u[:, 2] * root
    b2 = 1.0 - b0 - b1
    points: F64Array = b0[:, None] * a[tri] + b1[:, None] * b[tri] + b2[:, None] * c[tri]
    return points


def shadow_rays(
    rays: RayBatch,
    hits: HitBatch,
    normals: npt.ArrayLike,
    light: npt.ArrayLike,
    *,
    seed: int = 0,
    epsilon: float = 1e-4,
) -> tuple[RayBatch, IntArray]:
    """Spawn one shadow ray per hit towards a point light or a sampled area light.

    Parameters
    ----------
    rays : RayBatch
        The traced rays, ``n`` of them.
    hits : HitBatch
        Their closest hits; rays with ``prim < 0`` spawn nothing.
    normals : (F, 3) array_like of float
        Geometric normal of every triangle; hits on zero-normal triangles spawn
        nothing.
    light : (3,) or (k, 3, 3) array_like of float
        A point light position, or the triangles ``(k, vertex, xyz)`` of an area
        light. An area light is sampled once per hit: a triangle with probability
        proportional to its area, then a uniform point on it.
    seed : int
        Seed of the PCG64 generator (unused for a point light).
    epsilon : float
        Relative origin offset along the normal (module docstring). Default 1e-4.

    Returns
    -------
    rays : RayBatch
        ``m <= n`` rays. ``origin`` is the hit point offset towards the light's
        side of the surface; ``direction = light_point - origin`` (not
        normalised), so ``t = 1`` is the light point; ``tmin = 0`` and
        ``tmax = SHADOW_TMAX = 1 - 1e-4``. Trace them with ``query="any"``.
    source : (m,) int32 ndarray
        Index in ``rays`` of the ray each shadow ray belongs to, ascending.

    Raises
    ------
    InvalidInputError
        On mismatched lengths, bad normals or light, or a bad ``epsilon``/``seed``.

    Notes
    -----
    Hit points that face away from the light still get a ray (offset to the
    light's side, as pbrt does); shading zeroes their contribution by ``cos θ``.
    A light point that coincides with the origin gives a zero direction, which by
    the :class:`RayBatch` convention never hits anything.
    """
    eps = _check_epsilon(epsilon)
    source, points, normal, scale = _hit_frames(rays, hits, normals)
    rng = _rng(seed)
    target = _light_points(light, len(source), rng)
    origin = _offset(points, normal, target - points, eps * scale)
    direction = target - origin
    return RayBatch(origin.astype(REAL), direction.astype(REAL), 0.0, SHADOW_TMAX), source


def ambient_occlusion_rays(
    rays: RayBatch,
    hits: HitBatch,
    normals: npt.ArrayLike,
    *,
    n_per_hit: int = 1,
    radius: float | None = None,
    seed: int = 0,
    epsilon: float = 1e-4,
) -> tuple[RayBatch, IntArray]:
    """Spawn cosine-weighted ambient-occlusion rays of bounded length at every hit.

    Parameters
    ----------
    rays : RayBatch
        The traced rays, ``n`` of them.
    hits : HitBatch
        Their closest hits; rays with ``prim < 0`` spawn nothing.
    normals : (F, 3) array_like of float
        Geometric normal of every triangle; hits on zero-normal triangles spawn
        nothing.
    n_per_hit : int
        Rays per hit point, ``>= 1``.
    radius : float, optional
        Occlusion distance in world units (``tmax`` of the unit-length rays),
        ``> 0``. Default: a tenth of the diagonal of the hit points' bounding box
        (1 if that box is a point).
    seed : int
        Seed of the PCG64 generator.
    epsilon : float
        Relative origin offset along the normal (module docstring). Default 1e-4.

    Returns
    -------
    rays : RayBatch
        ``m · n_per_hit`` rays, the ``n_per_hit`` rays of one hit consecutive;
        unit directions, ``tmin = 0``, ``tmax = radius``. Trace with
        ``query="any"``; the occluded fraction is the AO estimate (cosine
        weighting makes it the unbiased irradiance-weighted estimator).
    source : (m · n_per_hit,) int32 ndarray
        Index in ``rays`` of the ray each AO ray belongs to.

    Raises
    ------
    InvalidInputError
        On mismatched lengths, bad normals, ``n_per_hit < 1``, a non-positive
        ``radius`` or a bad ``epsilon``/``seed``.
    """
    eps = _check_epsilon(epsilon)
    if isinstance(n_per_hit, bool) or not isinstance(n_per_hit, (int, np.integer)):
        raise InvalidInputError(f"n_per_hit: expected a positive int, got {n_per_hit!r}")
    if n_per_hit < 1:
        raise InvalidInputError(f"n_per_hit: expected a positive int, got {n_per_hit}")
    source, points, normal, scale = _hit_frames(rays, hits, normals)
    if radius is None:
        extent = np.ptp(points, axis=0) if len(points) else np.zeros(3)
        length = 0.1 * float(np.linalg.norm(extent))
        radius_value = length if length > 0.0 else 1.0
    else:
        try:
            radius_value = float(radius)
        except (TypeError, ValueError) as exc:
            raise InvalidInputError(f"radius: expected a float, got {radius!r}") from exc
        if not radius_value > 0.0:
            raise InvalidInputError(f"radius: expected a value > 0, got {radius_value}")
    rng = _rng(seed)
    count = int(n_per_hit)
    u = rng.random((len(source) * count, 2))
    normal = np.repeat(normal, count, axis=0)
    direction = cosine_hemisphere(normal, u[:, 0], u[:, 1])
    origin = _offset(np.repeat(points, count, axis=0), normal, None, eps * np.repeat(scale, count))
    batch = RayBatch(origin.astype(REAL), direction.astype(REAL), 0.0, radius_value)
    return batch, np.repeat(source, count).astype(INDEX)
