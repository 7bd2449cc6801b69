"""simgen.learn.streaming: a garment stream replayed from a CUDA graph gives the eager stream's
frames (GPU only; skipped on the CPU), and asking for one on the CPU is one clear error."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from simgen.errors import InputError


@pytest.fixture(scope="module")
def snug_model():
    """A small untrained SnugModel of the open body: 2 GRU layers of 16 on a 50-vertex garment (the
    graph replays whatever the weights are)."""
    from simgen.body import load
    from simgen.learn.snug import SnugModel, SnugNet

    torch.manual_seed(0)
    net = SnugNet(10, 79, 50, 80, hidden=16, layers=2)
    with torch.no_grad():
        net.template.skin_weights.zero_()[:, 0] = 1.0
        net.output_layer.weight.normal_(0.0, 0.3)
    return SnugModel(net, load("open"))


def _clip(frames: int = 12):
    from simgen.motion import load_motion

    m = load_motion("jumping_jacks")
    return (np.zeros((frames, 10), np.float32), m.poses[:frames].astype(np.float32),
            m.trans[:frames].astype(np.float32), float(m.fps))


def test_a_graphed_stream_needs_cuda(snug_model):
    from simgen.learn.evaluate import time_inference
    from simgen.learn.streaming import GraphedStream

    b, p, t, fps = _clip(2)
    with pytest.raises(InputError, match="CUDA device"):
        GraphedStream(snug_model, fps).step(*(torch.as_tensor(x) for x in (b[:1], p[:1], t[:1])))
    with pytest.raises(InputError, match="CUDA graph needs a CUDA device"):
        time_inference(snug_model, b, p, t, fps, device="cpu", postprocess=False, cuda_graph=True)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a GPU")
def test_graphed_frames_equal_the_eager_frames(snug_model):
    from simgen.learn.comparison.metrics import SnugStepper
    from simgen.learn.garment_model import StreamState
    from simgen.learn.streaming import GraphedStream

    dev = torch.device("cuda")
    stepper = SnugStepper(snug_model).to(dev)
    b, p, t, fps = _clip()
    b, p, t = (torch.as_tensor(x, device=dev) for x in (b, p, t))
    state, graphed, frames = StreamState(), GraphedStream(stepper, fps), []
    for i in range(len(p)):
        eager = stepper.step(state, b[i:i + 1], p[i:i + 1], t[i:i + 1], fps)
        replay = graphed.step(b[i:i + 1], p[i:i + 1], t[i:i + 1])
        assert torch.allclose(eager, replay, atol=1e-5), i
        frames.append(replay.clone())
    assert graphed.graph is not None  # frames 1.. were replays
    with pytest.raises(InputError, match="keeps the shapes it was recorded with"):
        graphed.step(b[:2], p[:2], t[:2])  # two bodies in a stream recorded for one
    assert float((frames[-1] - frames[1]).abs().max()) > 1e-3  # and they advanced (GRU state, pose)
