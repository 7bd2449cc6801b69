"""The sim's shared Warp toolkit, used by the energies, the solver and the linear solver:
scalar-generic types, Warp module naming, PSD projection, per-instance block reductions.

Every energy kernel is built by a factory for one scalar type (``wp.float32`` on the device,
``wp.float64`` for the finite-difference tests), so the very code the solver runs is what the
float64 tests check. The kernels of one energy file and one scalar type share one Warp module
(``<file module>.<scalar>``), so Warp's kernel cache works across runs and a float32 run never
compiles the float64 code.

Per-instance sums (the energy of each instance, the PCG's dot products) are segmented block
reductions (:func:`reduce_funcs`, :func:`launch_blocked`): elements are stored instance by instance,
so a block of ``REDUCE_BLOCK`` threads sums its first instance's share in a tile and adds it with
one atomic, and the elements of a second instance in the block (at an instance boundary) add theirs
directly. One atomic per element into one scalar per instance serialises on that address
(BENCHMARKS.md).
"""

import functools
from types import SimpleNamespace

import numpy as np
import warp as wp


__all__ = ["SCALARS", "scalar_types", "module_name", "math_funcs", "check_scalar", "resolve_outputs",
           "reduce_funcs", "launch_blocked", "REDUCE_BLOCK"]

SCALARS = (wp.float32, wp.float64)

# Threads per block of the reducing kernels on CUDA (Warp runs tile kernels one thread per block on
# the CPU, where the same code reduces blocks of one).
REDUCE_BLOCK = 256


def check_scalar(scalar) -> None:
    """Raise TypeError unless ``scalar`` is wp.float32 or wp.float64."""
    if scalar not in SCALARS:
        raise TypeError(f"scalar type must be wp.float32 or wp.float64, got {scalar!r}")


@functools.cache
def scalar_types(scalar) -> SimpleNamespace:
    """Vector and matrix types over ``scalar`` (Warp's named ones where they exist)."""
    check_scalar(scalar)
    f64 = scalar is wp.float64
    return SimpleNamespace(
        scalar=scalar,
        vec2=wp.vec2d if f64 else wp.vec2,
        vec3=wp.vec3d if f64 else wp.vec3,
        mat22=wp.mat22d if f64 else wp.mat22,
        mat33=wp.mat33d if f64 else wp.mat33,
        mat32=wp.types.matrix((3, 2), scalar),
        mat66=wp.types.matrix((6, 6), scalar),
    )


def module_name(file_module: str, scalar) -> str:
    """Warp module holding the kernels of one energy file for one scalar type."""
    return f"{file_module}.{scalar.__name__}"


@functools.cache
def math_funcs(scalar) -> SimpleNamespace:
    """Warp functions shared by the energies, for one scalar type.

    project_psd6(A) -> A+: the nearest positive semi-definite matrix of a symmetric 6x6 A
      (eigenvalues clamped at 0), by cyclic Jacobi sweeps.
    """
    t = scalar_types(scalar)
    mat66 = t.mat66
    # Jacobi converges quadratically; a 6x6 needs ~5 sweeps to float32 and ~7 to float64 accuracy,
    # the loop stops as soon as the off-diagonal part is negligible.
    sweeps = 10 if scalar is wp.float64 else 8
    rel_tol = scalar(1.0e-15 if scalar is wp.float64 else 1.0e-7)

    @wp.func
    def project_psd6(a_in: mat66):
        a = a_in
        v = wp.identity(n=6, dtype=scalar)
        norm2 = scalar(0.0)
        for i in range(6):
            for j in range(6):
                norm2 += a[i, j] * a[i, j]
        tol2 = norm2 * rel_tol * rel_tol
        for _sweep in range(sweeps):
            off2 = scalar(0.0)
            for p in range(5):
                for q in range(p + 1, 6):
                    off2 += a[p, q] * a[p, q]
            if off2 <= tol2:
                break
            for p in range(5):
                for q in range(p + 1, 6):
                    apq = a[p, q]
                    if apq * apq > tol2 * scalar(1.0e-4):
                        # Rotation J in the (p, q) plane that zeroes a[p, q]; a <- J^T a J, v <- v J.
                        theta = (a[q, q] - a[p, p]) / (scalar(2.0) * apq)
                        tt = scalar(1.0) / (wp.abs(theta) + wp.sqrt(theta * theta + scalar(1.0)))
                        if theta < scalar(0.0):
                            tt = -tt
                        c = scalar(1.0) / wp.sqrt(tt * tt + scalar(1.0))
                        s = tt * c
                        for k in range(6):
                            akp = a[k, p]
                            akq = a[k, q]
                            a[k, p] = c * akp - s * akq
                            a[k, q] = s * akp + c * akq
                        for k in range(6):
                            apk = a[p, k]
                            aqk = a[q, k]
                            a[p, k] = c * apk - s * aqk
                            a[q, k] = s * apk + c * aqk
                        for k in range(6):
                            vkp = v[k, p]
                            vkq = v[k, q]
                            v[k, p] = c * vkp - s * vkq
                            v[k, q] = s * vkp + c * vkq
        out = mat66()
        for e in range(6):
            lam = a[e, e]
            if lam > scalar(0.0):
                for i in range(6):
                    for j in range(6):
                        out[i, j] += lam * v[i, e] * v[j, e]
        return out

    return SimpleNamespace(project_psd6=project_psd6)


@functools.cache
def reduce_funcs(scalar) -> SimpleNamespace:
    """``block_add(out, instance_of, block, lane, i, n, value)``: adds each thread's value (element
    i < n; pass 0 past n) to ``out[instance_of[i]]`` by a segmented block reduction (module doc).
    Every thread of the block must reach the same call: the tile sum is a block-wide barrier, so a
    kernel computes its value under ``if i < n`` and calls this outside any branch that differs
    between threads."""
    zero = scalar(0.0)

    @wp.func
    def block_add(out: wp.array(dtype=scalar), instance_of: wp.array(dtype=wp.int32), block: int, lane: int,
                  i: int, n: int, value: scalar):
        first = instance_of[wp.min(block * wp.block_dim(), n - 1)]
        own = zero
        if i < n:
            if instance_of[i] == first:
                own = value
            else:
                wp.atomic_add(out, instance_of[i], value)
        total = wp.tile_sum(wp.tile(own))
        if lane == 0:
            wp.atomic_add(out, first, total[0])

    return SimpleNamespace(block_add=block_add)


def reduce_block(device) -> int:
    """Threads per block of the reducing kernels on ``device``."""
    return REDUCE_BLOCK if wp.get_device(device).is_cuda else 1


def launch_blocked(kernel, n: int, device, inputs: list) -> None:
    """Launch a reducing kernel over ``n`` elements in blocks; ``n`` is appended to ``inputs`` and the
    kernel reads its element as ``block * wp.block_dim() + lane`` from ``block, lane = wp.tid()``."""
    if n <= 0:
        return
    block = reduce_block(device)
    wp.launch_tiled(kernel, dim=[(n + block - 1) // block], block_dim=block, device=device, inputs=[*inputs, int(n)])


def resolve_outputs(energy, gradient, hessian):
    """Flags and arrays for a kernel launch from the optional outputs of an ``eval_*`` call.

    hessian may be a warp.sparse BsrMatrix (its ``values`` are used) or a values array. Returns
    (want_energy, want_gradient, want_hessian, energy, gradient, hessian_values); a missing output
    is passed to the kernel as None (a null array the kernel never touches).
    """
    values = getattr(hessian, "values", hessian)
    return int(energy is not None), int(gradient is not None), int(values is not None), energy, gradient, values


BROAD_PHASE_SPACING = 50.0  # [m] instances sit this far apart on a lattice in the broad-phase BVHs
#: Construction of the cloth's broad-phase trees (self-contact, impact filter): they are built once on
#: the rest shape and refit every substep, so the top-down SAH build (on the host, also for a GPU
#: tree; about 4 s for a solver's four trees at 64 T-shirts) is paid once for the best query time.
#: Warp's CUDA default, the LBVH, sorts by 10-bit Morton codes over all boxes, which across the
#: instance lattice are too coarse to order one garment (scripts/bvh_quality.py).
BVH_CONSTRUCTOR = "sah"


def instance_offsets(num_instances: int) -> np.ndarray:
    """(I, 3) float32 broad-phase offsets [m]: instance i on an 8 x 8 x n lattice of
    BROAD_PHASE_SPACING, so the boxes of copies that overlap in space (same body, other shapes) do
    not meet in a BVH shared by all instances, and coordinates stay small enough (<= 400 m for 512
    copies) for float32 boxes to keep sub-0.1 mm precision. Kernels still compare instances."""
    i = np.arange(num_instances)
    return (np.stack([i % 8, (i // 8) % 8, i // 64], axis=1) * BROAD_PHASE_SPACING).astype(np.float32)

