"""Built-in meshes generated in code, user meshes, and handle regions.

No downloads: the surface is a capsule (a cylinder closed by two hemispheres)
triangulated as a "cube sphere" stretched along z, and the volume is an
octopus-like body (an ellipsoid with eight arms) voxelized and split into
tetrahedra. Any OBJ/PLY/OFF/STL file works as a surface too
(:func:`load_surface`, through ``igl.read_triangle_mesh``).

Conventions: V is ``(n, 3)`` float64 vertex positions, F ``(f, 3)`` int64
triangles oriented outwards (counter-clockwise seen from outside), T ``(t, 4)``
int64 tetrahedra with positive volume, ``det[x1-x0, x2-x0, x3-x0] > 0``.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

__all__ = ["BUILTIN", "Mesh", "capsule", "end_regions", "load_surface", "octopus"]


@dataclass(frozen=True)
class Mesh:
    """A named mesh: ``V (n, 3)`` float64, ``F`` ``(f, 3)`` triangles or
    ``(t, 4)`` tetrahedra, int64."""

    name: str
    V: np.ndarray
    F: np.ndarray

    @property
    def is_volume(self) -> bool:
        return self.F.shape[1] == 4


def _grid_face(origin, u, v, nu: int, nv: int) -> tuple[np.ndarray, np.ndarray]:
    """A planar grid of (nu+1) x (nv+1) points origin + a u + b v, a in [0,1],
    b in [0,1], split into triangles oriented like u x v. Diagonals alternate
    per cell (a "union jack" pattern keeps the triangulation symmetric)."""
    a = np.linspace(0.0, 1.0, nu + 1)
    b = np.linspace(0.0, 1.0, nv + 1)
    A, B = np.meshgrid(a, b, indexing="ij")
    P = origin + A[..., None] * u + B[..., None] * v
    idx = np.arange((nu + 1) * (nv + 1)).reshape(nu + 1, nv + 1)
    i00, i10 = idx[:-1, :-1], idx[1:, :-1]
    i01, i11 = idx[:-1, 1:], idx[1:, 1:]
    flip = ((np.arange(nu)[:, None] + np.arange(nv)[None, :]) % 2).astype(bool)
    # Cell (a,b): corners 00, 10, 11, 01 counter-clockwise around u x v.
    t1 = np.where(flip[..., None], np.stack([i00, i10, i01], -1), np.stack([i00, i10, i11], -1))
    t2 = np.where(flip[..., None], np.stack([i10, i11, i01], -1), np.stack([i00, i11, i01], -1))
    F = np.concatenate([t1.reshape(-1, 3), t2.reshape(-1, 3)])
    return P.reshape(-1, 3), F


def _merge_duplicates(V: np.ndarray, F: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Merges vertices closer than ``tol`` (grid faces share their edges)."""
    keys = np.round(V / tol).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    return V[first], inverse.reshape(-1)[F]


def _box_surface(k: int, half_length: float) -> tuple[np.ndarray, np.ndarray]:
    """Surface of the box [-1,1]^2 x [-1-h, 1+h] with grid spacing 2/k
    (k even), triangles oriented outwards."""
    h = half_length
    nz = int(round(k * (1 + h)))  # cells along z on the side faces
    ex, ey, ez = np.eye(3)
    faces = [
        # (origin, u, v, nu, nv) with u x v the outward normal
        (np.array([1.0, -1, -1 - h]), 2 * ey, 2 * (1 + h) * ez, k, nz),  # +x
        (np.array([-1.0, 1, -1 - h]), -2 * ey, 2 * (1 + h) * ez, k, nz),  # -x
        (np.array([1.0, 1, -1 - h]), -2 * ex, 2 * (1 + h) * ez, k, nz),  # +y
        (np.array([-1.0, -1, -1 - h]), 2 * ex, 2 * (1 + h) * ez, k, nz),  # -y
        (np.array([-1.0, -1, 1 + h]), 2 * ex, 2 * ey, k, k),  # +z
        (np.array([-1.0, 1, -1 - h]), 2 * ex, -2 * ey, k, k),  # -z
    ]
    Vs, Fs, offset = [], [], 0
    for origin, u, v, nu, nv in faces:
        P, T = _grid_face(origin, u, v, nu, nv)
        Vs.append(P)
        Fs.append(T + offset)
        offset += len(P)
    return _merge_duplicates(np.concatenate(Vs), np.concatenate(Fs), tol=0.25 / k)


def _cube_to_sphere(P: np.ndarray) -> np.ndarray:
    """Maps the surface of [-1,1]^3 onto the unit sphere with little
    distortion (x' = x sqrt(1 - y^2/2 - z^2/2 + y^2 z^2/3), cyclic)."""
    x, y, z = P[:, 0], P[:, 1], P[:, 2]
    x2, y2, z2 = x * x, y * y, z * z
    return np.stack([
        x * np.sqrt(1 - y2 / 2 - z2 / 2 + y2 * z2 / 3),
        y * np.sqrt(1 - z2 / 2 - x2 / 2 + z2 * x2 / 3),
        z * np.sqrt(1 - x2 / 2 - y2 / 2 + x2 * y2 / 3),
    ], -1)


def capsule(resolution: int = 64, half_length: float = 2.0, radius: float = 1.0) -> Mesh:
    """Closed capsule surface along z: a cylinder of the given radius and
    length ``2 half_length radius`` closed by two hemispheres.

    Built as a box surface gridded at spacing 2/resolution whose end parts are
    mapped to the sphere and whose middle part to the cylinder, so triangles are
    nearly uniform and have no poles. Vertices: about
    ``6 r^2 + 4 r^2 half_length`` (r = resolution): 57,346 for the default.
    """
    if resolution < 2 or resolution % 2:
        raise ValueError(f"capsule: resolution must be an even integer >= 2, got {resolution}")
    if half_length < 0 or radius <= 0:
        raise ValueError(f"capsule: half_length must be >= 0 and radius > 0, got {half_length}, {radius}")
    P, F = _box_surface(resolution, half_length)
    z_centre = np.clip(P[:, 2], -half_length, half_length)
    local = P.copy()
    local[:, 2] -= z_centre  # in [-1, 1]^3: the end caps are cube faces, the middle a square tube
    V = _cube_to_sphere(local)
    V[:, 2] += z_centre
    return Mesh(f"capsule_r{resolution}", V * radius, F.astype(np.int64))


# Kuhn (Freudenthal) split of the unit cube into 6 tetrahedra, one per axis
# order: the path 000 -> 111 that raises the coordinates in that order.
# Neighbouring cubes split their shared face the same way, so the mesh is conforming.
def _kuhn_tets() -> np.ndarray:
    tets = []
    for order in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        corner = np.zeros(3, dtype=np.int64)
        path = [corner.copy()]
        for axis in order:
            corner[axis] = 1
            path.append(corner.copy())
        tets.append([c[0] * 4 + c[1] * 2 + c[2] for c in path])  # corner id = 4x + 2y + z
    return np.array(tets, dtype=np.int64)


def _octopus_inside(P: np.ndarray, arms: int = 8) -> np.ndarray:
    """Points inside an octopus-like body: an ellipsoid head and ``arms``
    tapered arms curling down and out from its base (unit ~ 1)."""
    x, y, z = P[:, 0], P[:, 1], P[:, 2]
    inside = (x / 0.75) ** 2 + (y / 0.75) ** 2 + ((z - 0.55) / 0.65) ** 2 <= 1.0
    t = np.linspace(0.0, 1.0, 48)
    for a in range(arms):
        phi = 2 * math.pi * a / arms
        # arm centre line: leaves the head's base, runs out and down, tip curls up
        reach = 0.35 + 1.45 * t
        cx, cy = reach * math.cos(phi), reach * math.sin(phi)
        cz = 0.25 - 0.55 * np.sin(math.pi * 0.5 * t) + 0.25 * t**3
        rad = 0.24 * (1 - 0.7 * t)
        d2 = (x[:, None] - cx) ** 2 + (y[:, None] - cy) ** 2 + (z[:, None] - cz) ** 2
        inside |= (d2 <= rad**2).any(axis=1)
    return inside


def octopus(resolution: int = 24) -> Mesh:
    """Tetrahedral octopus: the cubes of a grid of spacing ``2 / resolution``
    whose centres lie inside :func:`_octopus_inside`, 6 tetrahedra per cube.
    24,054 tetrahedra (5,827 vertices) for the default resolution; the body
    stands on z = 0."""
    if resolution < 4:
        raise ValueError(f"octopus: resolution must be >= 4, got {resolution}")
    h = 2.0 / resolution
    lo, hi = np.array([-2.1, -2.1, -0.6]), np.array([2.1, 2.1, 1.3])
    counts = np.ceil((hi - lo) / h).astype(np.int64)
    cells = np.stack(np.meshgrid(*[np.arange(c) for c in counts], indexing="ij"), -1).reshape(-1, 3)
    occupied = _octopus_inside(lo + (cells + 0.5) * h).reshape(tuple(counts))
    keep = np.argwhere(_fill_edge_contacts(occupied))
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=np.int64)
    node = keep[:, None, :] + corners[None]  # (cubes, 8, 3) grid coordinates
    strides = np.array([(counts[1] + 1) * (counts[2] + 1), counts[2] + 1, 1])
    node_id = node @ strides
    T = node_id[:, _kuhn_tets()].reshape(-1, 4)
    used, T = np.unique(T, return_inverse=True)
    T = T.reshape(-1, 4)
    grid = np.stack([used // strides[0], (used // strides[1]) % (counts[1] + 1), used % (counts[2] + 1)], -1)
    V = lo + grid * h
    V[:, 2] -= V[:, 2].min()
    return Mesh(f"octopus_r{resolution}", V, _orient_positive(V, T))


def _fill_edge_contacts(occupied: np.ndarray) -> np.ndarray:
    """Adds cubes until no two cubes touch along an edge only (a diagonal
    2 x 2 pattern in some axis plane), so the boundary surface is manifold."""
    occupied = occupied.copy()
    while True:
        changed = False
        for a, b in ((0, 1), (0, 2), (1, 2)):
            moved = np.moveaxis(occupied, (a, b), (0, 1))  # a view: writes reach ``occupied``
            c00, c11 = moved[:-1, :-1], moved[1:, 1:]
            c10, c01 = moved[1:, :-1], moved[:-1, 1:]
            diagonal = c00 & c11 & ~c10 & ~c01
            anti = c10 & c01 & ~c00 & ~c11
            if diagonal.any() or anti.any():
                c10 |= diagonal  # fill one of the two empty cubes of each pattern
                c00 |= anti
                changed = True
        if not changed:
            return occupied


def _orient_positive(V: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Swaps two vertices of every tetrahedron with negative volume."""
    D = V[T[:, 1:]] - V[T[:, :1]]
    flip = np.linalg.det(D) < 0
    T = T.copy()
    T[flip, 1], T[flip, 2] = T[flip, 2], T[flip, 1].copy()
    return T


def load_surface(path: str) -> Mesh:
    """A triangle mesh from an OBJ/OFF/PLY/STL/... file (``igl.read_triangle_mesh``)."""
    import igl

    if not os.path.isfile(path):
        raise FileNotFoundError(f"load_surface: no mesh file at {path!r}")
    V, F = igl.read_triangle_mesh(path)
    if V.ndim != 2 or V.shape[1] != 3 or F.ndim != 2 or F.shape[1] != 3 or len(F) == 0:
        raise ValueError(f"load_surface: {path!r} is not a 3D triangle mesh (V {V.shape}, F {F.shape})")
    V, F = np.asarray(V, dtype=np.float64), np.asarray(F, dtype=np.int64)
    used = np.unique(F)
    if len(used) != len(V):  # drop unreferenced vertices: they would make the Laplacian singular
        remap = np.full(len(V), -1, dtype=np.int64)
        remap[used] = np.arange(len(used))
        V, F = V[used], remap[F]
    return Mesh(os.path.splitext(os.path.basename(path))[0], V, F)


#: name -> builder of the built-in meshes (keyword arguments allowed).
BUILTIN = {"capsule": capsule, "octopus": octopus}


def end_regions(V: np.ndarray, fraction: float = 0.1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Handle regions of a surface: the vertices in the lowest and highest
    ``fraction`` of its longest bounding-box axis. Returns (low indices,
    high indices, unit axis)."""
    extent = V.max(0) - V.min(0)
    axis = int(np.argmax(extent))
    coord = V[:, axis]
    lo, hi = coord.min(), coord.max()
    low = np.flatnonzero(coord <= lo + fraction * (hi - lo))
    high = np.flatnonzero(coord >= hi - fraction * (hi - lo))
    direction = np.zeros(3)
    direction[axis] = 1.0
    return low, high, direction
