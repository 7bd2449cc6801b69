"""SoftSMPL's data augmentations for captured data (thesis sections 3.3.2 and 3.4.1): mirroring a
sequence, and motion transfer, where each subject plays the clips it lacks with its own regressor."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from simgen.body import load
from simgen.body.torch_lbs import TorchBody
from simgen.errors import InputError
from simgen.learn.softtissue.data import (SoftTissueData, mirror_vertex_map, synthetic_softtissue_data,
                                          with_mirrored)

# _one_thread: that module's autouse fixture (one torch thread), taken into this module too
from test_softtissue_models import _one_thread, _tiny_body, _tiny_config  # noqa: F401


def test_a_mirrored_sequence_is_the_reflection_of_the_posed_body():
    # The posed mirror image must be the original's posed body reflected across x = 0, vertex for
    # vertex through the template's mirror map: joints swapped and reflected, Delta taken from the
    # mirror vertex with x negated. Checked on the full open body (left-right symmetric to 0.3 mm).
    from simgen.learn.softtissue.dyna import posed_vertices

    body = load("open")
    src = synthetic_softtissue_data(body, motions=("walk",), subjects=1, frames=6)
    s = src.sequences[0]
    s.betas[:] = 0.0                      # the shape space is only taken as symmetric: test the rest exactly
    # a Delta that is not itself symmetric: different on the two sides and in all coordinates
    rng = np.random.default_rng(0)
    s.displacements = (s.displacements + rng.normal(0, 0.004, s.displacements.shape)).astype(np.float32)
    both = with_mirrored(SoftTissueData([s], src.body, src.faces, src.template, src.source))
    assert [q.name for q in both.sequences] == [s.name, f"{s.name}_mirror"]
    m = both.sequences[1]
    assert m.meta["mirrored"] and m.subject == s.subject and m.motion == s.motion
    vmap = mirror_vertex_map(body.v_template)
    assert np.array_equal(vmap[vmap], np.arange(body.num_vertices))

    tb = TorchBody(body, dtype=torch.float64)

    def posed(q):
        return posed_vertices(tb, torch.as_tensor(q.displacements, dtype=torch.float64),
                              torch.as_tensor(q.betas, dtype=torch.float64),
                              torch.as_tensor(q.poses, dtype=torch.float64),
                              torch.as_tensor(q.trans, dtype=torch.float64)).numpy()

    x, xm = posed(s), posed(m)
    reflected = x[:, vmap] * np.array([-1.0, 1.0, 1.0])
    err = np.linalg.norm(xm - reflected, axis=-1).max()
    assert err < 1.5e-3, err                                   # the template's own asymmetry is 0.3 mm
    assert np.linalg.norm(xm - x, axis=-1).max() > 20 * err    # and the mirror image really is another motion
    again = with_mirrored(both)                                # mirrored sequences are not mirrored twice
    assert len(again.sequences) == 2


def test_mirroring_refuses_an_asymmetric_body():
    body = _tiny_body()                                        # every 60th triangle: not symmetric
    data = synthetic_softtissue_data(body, motions=("jump",), subjects=1, frames=4)
    with pytest.raises(InputError, match="not left-right symmetric"):
        with_mirrored(data)


def test_motion_transfer_fills_the_clips_a_subject_lacks(tmp_path):
    from simgen.learn.checkpoint import load_model
    from simgen.learn.softtissue.train import _Run, train_softtissue
    from simgen.learn.softtissue.transfer import missing_clips

    body = _tiny_body()
    full = synthetic_softtissue_data(body, motions=("jump", "walk", "run", "squat"), subjects=3, frames=12)
    # a capture: s1 never walked, s2 never ran; squat is held out
    data = full.subset(lambda s: s.name not in ("s1_walk", "s2_run"))
    lacks = missing_clips(data.split(["squat"])[0])
    assert {k: [s.name for s in v] for k, v in lacks.items()} == {"s1": ["s0_walk"], "s2": ["s0_run"]}
    assert missing_clips(full) == {}                          # a store where every shape does every clip

    cfg = _tiny_config(test_motions="squat", reg_epochs=4)
    train_softtissue(data, tmp_path / "m", body=body, config=cfg)
    folder = tmp_path / "m" / "softtissue"
    saved = json.loads((folder / "regressor" / "config.json").read_text())["training"]["motion_transfer"]
    assert {k: v["clips"] for k, v in saved.items()} == {"s1": ["walk"], "s2": ["run"]}
    assert sorted(p.name for p in (folder / "transfer").iterdir()) == ["s1", "s2"]

    # the transferred item: s0's walk (its pose code and root motion), s1's betas, and s1's own regressor's
    # prediction for them as the target
    run = _Run(data, cfg, torch.device("cpu"), body)
    for k in ("pose_ae", "soft_ae", "regressor"):
        run.nets[k] = load_model(folder / k, identity=run.identity)
    run.prepare_regressor(cfg, folder)                        # loads the kept subject regressors
    assert len(run.items) == len(run.train.sequences) + 2
    index = {s.name: i for i, s in enumerate(run.train.sequences)}
    gamma, codes, betas = run.items[len(run.train.sequences)]
    src = run._encoded(run.train, index["s0_walk"])
    assert torch.equal(gamma, src[0])
    assert torch.allclose(betas, torch.as_tensor(data.sequences[[s.name for s in data.sequences].index("s1_jump")].betas))
    r1 = load_model(folder / "transfer" / "s1", identity=run.identity)
    with torch.no_grad():
        assert torch.allclose(codes, r1(gamma[None], betas[None])[0])
    assert not torch.allclose(codes, src[1])                  # not s0's own codes copied over

    # a rerun of the finished run keeps the record; a restart with another code size trains new subject
    # regressors for its own autoencoder (the kept ones play codes of the old one)
    train_softtissue(data, tmp_path / "m", body=body, config=cfg)
    again = json.loads((folder / "regressor" / "config.json").read_text())["training"]["motion_transfer"]
    assert again == saved
    bigger = _tiny_config(test_motions="squat", reg_epochs=4, ae_latent=6)
    assert train_softtissue(data, tmp_path / "m", body=body, config=bigger, resume=False).stage == "done"
    assert load_model(folder / "transfer" / "s1", identity=run.identity).latent == 6

    # without motion transfer nothing is played, and the regressor trains on one subject per clip
    one_cfg = _tiny_config(test_motions="squat", motion_transfer=False, reg_epochs=1)
    one = _Run(data, one_cfg, torch.device("cpu"), body)
    one.prepare_regressor(one_cfg, tmp_path / "one")
    assert len(one.items) == len({(s.motion, s.subject) for s in one.train.sequences}) == 3
    assert len({s.subject for s in one.train.sequences}) == 3 and one.transfer == {}
    assert not (tmp_path / "one" / "transfer").exists()
