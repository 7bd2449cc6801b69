"""Ground truth of the fit and wrinkle regressors (simgen.dataset.groundtruth, thesis eqs. 4.4 and 4.5).

Operator properties are checked on the garment mesh against invariants (linearity, translation
equivariance, planes stay planar, Taubin shrinks far less than Laplacian smoothing); the skinning
transforms against the body's own numpy forward pass. On a small generated store (tshirt_1k,
shapes 0 and beta_1 = +2, a clip that starts in the rest pose and blends into jumping jacks) the
decomposition is checked: skinning T_c + fit + wrinkle gives back the simulated frames, the fit
displacement vanishes at beta = 0, and the wrinkle displacement is small over the protocol's rest
frames compared with during the motion. ~15 s on 2 CPU cores.
"""

import numpy as np
import pytest

from simgen import body as body_pkg
from simgen.dataset import generate_dataset, open_dataset, parse_spec
from simgen.dataset.groundtruth import (
    SmoothingParams,
    fit_displacement,
    reconstruct,
    skinning_transforms,
    smooth_garment,
    wrinkle_displacements,
)
from simgen.errors import InputError
from simgen.garment.library import load_garment

# Below this the fit displacement at beta = 0 counts as zero: the fit simulation at beta = 0 is the
# template relaxation followed by the same rest phase, so only a cloth still settling could move it.
FIT_ZERO_TOL = 5.0e-4  # [m]
RECONSTRUCT_TOL = 1.0e-5  # [m], the bound; float32 storage, float64 arithmetic


@pytest.fixture(scope="module")
def shirt():
    b = body_pkg.load("open")
    return b, load_garment("tshirt_1k", body=b)


def test_smoothing_is_linear_and_translation_equivariant(shirt):
    _, g = shirt
    rng = np.random.default_rng(0)
    x, y = g.vertices, g.vertices + 0.01 * rng.standard_normal(g.vertices.shape)
    p = SmoothingParams()
    np.testing.assert_allclose(smooth_garment(2 * x - y, g.faces, p), 2 * smooth_garment(x, g.faces, p)
                               - smooth_garment(y, g.faces, p), atol=1e-12)
    c = np.array([0.3, -1.2, 4.0])
    np.testing.assert_allclose(smooth_garment(x + c, g.faces, p), smooth_garment(x, g.faces, p) + c, atol=1e-12)


def test_smoothing_keeps_planes_and_removes_noise(shirt):
    _, g = shirt
    rng = np.random.default_rng(1)
    # Any point set on a plane stays on it (every step is an affine combination of neighbours).
    n = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    flat = g.vertices - np.outer(g.vertices @ n - 0.1, n)
    sm = smooth_garment(flat, g.faces, SmoothingParams(iterations=20))
    np.testing.assert_allclose(sm @ n, 0.1, atol=1e-12)
    # White noise (1 mm per vertex) loses most of its energy: its high-frequency part is damped
    # (by the operator's linearity, smoothing noisy = smoothing the garment + smoothing the noise).
    noise = 1e-3 * rng.standard_normal(g.vertices.shape)
    left = smooth_garment(g.vertices + noise, g.faces) - smooth_garment(g.vertices, g.faces)
    assert np.mean(left ** 2) < 0.3 * np.mean(noise ** 2)


def test_taubin_shrinks_far_less_than_laplacian(shirt):
    _, g = shirt
    x = g.vertices

    def spread(v):
        return np.mean(np.linalg.norm(v - v.mean(0), axis=1))

    taubin = spread(smooth_garment(x, g.faces, SmoothingParams(method="taubin", iterations=10)))
    lap = spread(smooth_garment(x, g.faces, SmoothingParams(method="laplacian", iterations=10, lam=0.5)))
    s0 = spread(x)
    assert abs(s0 - taubin) < 0.2 * abs(s0 - lap) and lap < s0
    fixed = smooth_garment(x, g.faces, SmoothingParams(boundary="fixed"))
    from simgen.garment.mesh import edge_face_counts

    e, c = edge_face_counts(g.faces)
    boundary = np.unique(e[c == 1])
    np.testing.assert_array_equal(fixed[boundary], x[boundary])
    assert np.max(np.abs(fixed - x)) > 1e-4
    with pytest.raises(InputError, match="mu must be below -lam"):
        SmoothingParams(mu=-0.4)


def test_skinning_transforms_match_body_forward(shirt):
    b, _ = shirt
    rng = np.random.default_rng(2)
    T = 5
    betas = rng.normal(size=(T, 4))
    poses = 0.4 * rng.normal(size=(T, 24, 3))
    trans = rng.normal(size=(T, 3))
    A = skinning_transforms(b, betas, poses, trans)
    np.testing.assert_allclose(A, b.forward(betas, poses, trans).transforms, atol=1e-12)
    # Rest pose, no translation: every joint transform is the identity, for any shape.
    A0 = skinning_transforms(b, betas[:1], np.zeros((1, 24, 3)), np.zeros((1, 3)))
    np.testing.assert_allclose(A0[0], np.broadcast_to(np.eye(4), (24, 4, 4)), atol=1e-12)


def test_wrinkle_and_reconstruct_are_inverse(shirt):
    b, g = shirt
    rng = np.random.default_rng(3)
    T = 4
    A = skinning_transforms(b, rng.normal(size=(T, 3)), 0.5 * rng.normal(size=(T, 24, 3)), rng.normal(size=(T, 3)))
    tc = smooth_garment(g.vertices, g.faces)
    dg = 0.01 * rng.normal(size=tc.shape)
    x = rng.normal(size=(T, g.num_vertices, 3))
    w = wrinkle_displacements(x, A, g.skin_weights, tc, dg)
    np.testing.assert_allclose(reconstruct(tc, dg, w, A, g.skin_weights), x, atol=1e-9)
    # Rest pose without translation: unposing is the identity, so the wrinkle is x - T_c - Delta_G.
    # (to 1e-6 m: the stored weights sum to 1 only to float32 precision, so the blend of identities
    # is (1 + O(1e-7)) I).
    I = np.broadcast_to(np.eye(4), (T, 24, 4, 4))
    np.testing.assert_allclose(wrinkle_displacements(x, I, g.skin_weights, tc, dg), x - tc - dg, atol=1e-6)
    np.testing.assert_allclose(fit_displacement(tc, tc, g.faces), smooth_garment(tc, g.faces) - tc, atol=1e-15)


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """tshirt_1k, shapes {0, beta_1 = +2}, one clip: 6 frames blending from the rest pose into
    jumping jacks (frame 30 onwards), 9 frames kept."""
    from simgen.motion import blend_from_rest, load_motion, save_motion
    from simgen.motion.clip import MotionClip

    tmp = tmp_path_factory.mktemp("gt")
    jj = load_motion("jumping_jacks")
    clip = MotionClip("rest_to_jacks", jj.fps, jj.poses[30:40], jj.trans[30:40], {})
    save_motion(blend_from_rest(clip, 6), tmp / "rest_to_jacks.npz")
    spec = parse_spec({
        "name": "gt",
        "garment": {"names": ["tshirt_1k"], "material": "cotton"},
        "shapes": {"generator": "list", "list": [{"id": "zero", "betas": []}, {"id": "wide", "betas": [0.0, 2.0]}]},
        "motions": {"library": [], "files": ["rest_to_jacks.npz"], "max_frames": 9},
        "solver": {"device": "cpu"},
        # A 6-frame ramp: over 3, the cloth on the wide shape still swings in the rest frames now that
        # the solver's three Newton iterations no longer damp it (SolverConfig's doc).
        "protocol": {"relax_frames": 2, "ramp_frames": 6, "rest_frames": 3},
    }, source="gt.toml", base_dir=tmp)
    generate_dataset(spec, out=str(tmp / "store"))
    return open_dataset(tmp / "store")


def test_reconstruction_reproduces_simulation(store):
    tpl = store.template
    for sid in store.sequence_ids():
        seq = store.sequence(sid)
        gt = store.groundtruth(sid)
        fit = store.fit(seq["attrs"]["shape_id"])
        rec = reconstruct(tpl["smoothed"], fit["fit_displacement"], gt["wrinkle"], gt["transforms"],
                          tpl["skin_weights"])
        assert np.max(np.abs(rec - seq["garment_vertices"])) < RECONSTRUCT_TOL
        # The body the wrinkles are unposed with is the one the cloth was simulated on: the cloth's
        # centroid follows the pelvis and the unposed cloth stays near the fitted template.
        assert np.mean(np.linalg.norm(gt["wrinkle"], axis=2)) < 0.05


def test_fit_displacement(store):
    tpl = store.template
    zero = store.fit("zero")
    assert np.max(np.abs(zero["fit_displacement"])) < FIT_ZERO_TOL
    wide = store.fit("wide")
    d = np.linalg.norm(wide["fit_displacement"], axis=1)
    assert d.max() > 5 * FIT_ZERO_TOL  # a wider body does move the garment
    # Eq. 4.4 on the stored arrays.
    np.testing.assert_allclose(wide["fit_displacement"],
                               smooth_garment(wide["vertices"], tpl["faces"], SmoothingParams(
                                   **tpl["smoothing"])) - tpl["smoothed"], atol=2e-6)
    # T_c is the smoothed relaxation T_r, and T_r is the fit at beta = 0 (no root translation).
    np.testing.assert_allclose(zero["vertices"], tpl["vertices"], atol=FIT_ZERO_TOL)
    assert 1e-4 < np.max(np.abs(tpl["vertices"] - tpl["smoothed"])) < 0.03


def test_wrinkles_small_at_rest_large_in_motion(store):
    """Over the protocol's rest frames the body holds the clip's first frame (the rest pose here):
    the wrinkle displacement there is only what the smoothing removed; once the arms come down it
    is several times larger."""
    body = store.load_body()
    tpl = store.template
    for sid in store.sequence_ids():
        seq = store.sequence(sid)
        rest = seq["rest_garment_vertices"]
        assert len(rest) == 3
        A0 = skinning_transforms(body, seq["betas"][:1], seq["poses"][:1], seq["trans"][:1])
        np.testing.assert_allclose(seq["poses"][0], 0.0, atol=1e-6)
        fit = store.fit(seq["attrs"]["shape_id"])
        w_rest = wrinkle_displacements(rest, np.repeat(A0, len(rest), 0), tpl["skin_weights"], tpl["smoothed"],
                                       fit["fit_displacement"])
        w_motion = store.groundtruth(sid)["wrinkle"]
        rest_mean = np.mean(np.linalg.norm(w_rest, axis=2))
        motion_mean = np.mean(np.linalg.norm(w_motion[-3:], axis=2))
        print(f"{sid}: wrinkle at rest {rest_mean * 1e3:.2f} mm, in motion {motion_mean * 1e3:.2f} mm")
        assert rest_mean < 0.3 * motion_mean, (sid, rest_mean, motion_mean)
