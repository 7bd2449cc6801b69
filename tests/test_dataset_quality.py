"""Membrane strain of simulated frames (simgen.dataset.quality.triangle_strain) against closed forms:
the largest principal stretch of a deformation gradient applied to a mesh, frame by frame."""

from __future__ import annotations

import numpy as np

from simgen.dataset.quality import STRAIN_CHUNK_FRAMES, strain_summary, triangle_rest_inverse, triangle_strain


def _sheet(n: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """A wavy sheet of 2 (n-1)^2 triangles [m], not in a coordinate plane."""
    u, v = np.meshgrid(np.linspace(0.0, 0.3, n), np.linspace(0.0, 0.2, n), indexing="ij")
    x = np.stack([u, v, 0.02 * np.sin(7.0 * u) * np.cos(5.0 * v)], axis=-1).reshape(-1, 3)
    k = np.arange(n * n).reshape(n, n)
    a, b, c, d = k[:-1, :-1].ravel(), k[1:, :-1].ravel(), k[1:, 1:].ravel(), k[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return x, faces


def test_strain_of_linear_maps_is_their_largest_singular_value_minus_one():
    """Each frame is the rest mesh through a linear map A (rotation, stretch, shear): on a flat
    sheet every triangle's F^T F is that of A restricted to the sheet's plane, so its strain is
    the largest singular value of A on the plane minus one; frames span several chunks."""
    rng = np.random.default_rng(3)
    x, faces = _sheet()
    x[:, 2] = 0.0                                         # flat: the plane is xy
    inv = triangle_rest_inverse(x, faces)
    T = 2 * STRAIN_CHUNK_FRAMES + 3
    maps = [np.eye(3) + 0.4 * rng.normal(size=(3, 3)) for _ in range(T)]
    frames = np.stack([x @ A.T + rng.normal(size=3) for A in maps])
    s = triangle_strain(frames, faces, inv)
    assert s.shape == (T, len(faces))
    expected = np.array([np.linalg.svd(A[:, :2], compute_uv=False)[0] - 1.0 for A in maps])
    np.testing.assert_allclose(s, np.repeat(expected[:, None], len(faces), 1), atol=1e-12)
    mean, mx = strain_summary(frames.astype(np.float32), faces, inv)   # float32 frames, as stored
    np.testing.assert_allclose(mx, expected, atol=1e-5)
    np.testing.assert_allclose(mean, expected, atol=1e-5)


def test_strain_is_zero_at_rest_and_under_rigid_motion_and_one_frame_works():
    x, faces = _sheet()
    inv = triangle_rest_inverse(x, faces)
    q, _ = np.linalg.qr(np.random.default_rng(0).normal(size=(3, 3)))
    moved = x @ q.T + np.array([0.1, -2.0, 0.3])
    assert np.abs(triangle_strain(x, faces, inv)).max() < 1e-12
    assert np.abs(triangle_strain(np.stack([x, moved]), faces, inv)).max() < 1e-12
    # One triangle stretched 30% along its first edge, others untouched: only it reads 0.3.
    stretched = x.copy()
    f0 = faces[0]
    stretched[f0[1]] = x[f0[0]] + 1.3 * (x[f0[1]] - x[f0[0]])
    s = triangle_strain(stretched, faces, inv)
    assert s.shape == (len(faces),) and s[0] > 0.3 - 1e-12
    untouched = [i for i, f in enumerate(faces) if f0[1] not in f]
    assert np.abs(s[untouched]).max() < 1e-12


def test_the_device_stretch_of_the_frame_statistics_is_this_measure_and_skips_pinched_triangles():
    """simgen.sim.frame_stats.triangle_stretch_max (the pool's per-frame stretch, float32 on the
    device) on two copies of a sheet under different linear maps: each copy's largest stretch is
    triangle_strain's, and with one vertex of the most stretched triangle at a body
    self-intersection the regular maximum is the largest of the other triangles."""
    import warp as wp

    from simgen.sim.frame_stats import triangle_stretch_max

    rng = np.random.default_rng(5)
    x, faces = _sheet()
    inv = triangle_rest_inverse(x, faces)
    n, f = len(x), len(faces)
    frames = np.stack([x @ (np.eye(3) + 0.3 * rng.normal(size=(3, 3))).T for _ in range(2)])   # (2, V, 3)
    frames[1, 14] += [0.05, 0.03, 0.02]      # a spike: the triangles around vertex 14 stretch most
    want = triangle_strain(frames, faces, inv)                                                    # (2, F)
    assert 14 in faces[int(np.argmax(want[1]))]
    self_hit = np.zeros(2 * n, dtype=np.int32)
    self_hit[n + 14] = 1                     # copy 1's most stretched triangles are pinched
    pinched = np.any(self_hit[n:][faces] != 0, axis=1)
    dev = "cpu"
    arr = lambda a, t: wp.array(np.ascontiguousarray(a), dtype=t, device=dev)   # noqa: E731
    out, out_regular = wp.zeros(2, dtype=wp.float32, device=dev), wp.zeros(2, dtype=wp.float32, device=dev)
    out.fill_(-1.0)
    out_regular.fill_(-1.0)
    wp.launch(triangle_stretch_max, dim=2 * f, device=dev,
              inputs=[arr(frames.reshape(-1, 3).astype(np.float32), wp.vec3),
                      arr(np.concatenate([faces, faces + n]).astype(np.int32), wp.int32),
                      arr(np.concatenate([inv, inv]).astype(np.float32), wp.mat22),
                      arr(np.repeat([0, 1], f).astype(np.int32), wp.int32), arr(np.ones(2, np.int32), wp.int32),
                      arr(self_hit, wp.int32)], outputs=[out, out_regular])
    np.testing.assert_allclose(out.numpy(), want.max(axis=1), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(out_regular.numpy(), [want[0].max(), want[1][~pinched].max()], rtol=1e-5, atol=1e-6)
    assert want[1][~pinched].max() < want[1].max() - 0.1
