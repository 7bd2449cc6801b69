"""Frame-by-frame inference replayed from a CUDA graph.

A garment model's frame (motion features, GRU step, the garment's shape and skinning: the
``step(state, betas, pose, trans, fps)`` of :class:`~simgen.learn.garment_model.GarmentModel` and
of the SNUG-type steppers) is a few hundred small kernels: on a GPU its time is the launches, not
the arithmetic. :class:`GraphedStream` records one frame of a model once into a CUDA graph
(``torch.cuda.CUDAGraph``) and replays it for every later frame: the inputs are copied into the
graph's own buffers, and the GRU state and the previous frame (the velocity features' history)
are carried from one replay to the next inside the graph.

The first frame of a stream runs eagerly (its features have no previous frame: zero velocity) and
gives the state the recorded frame starts from. The collision post-process (a Warp BVH query) is
not recorded: a graphed stream predicts without it.
"""

from __future__ import annotations

import torch

from simgen.errors import InputError

__all__ = ["GraphedStream"]


class GraphedStream:
    """One stream of N garments (one per body) whose frames replay a CUDA graph.

    model: anything with ``step(state, betas (N, B), pose (N, 24, 3), trans (N, 3), fps, *,
    postprocess)`` -> vertices [m] (N, V, 3), on a CUDA device; fps [1/s]: the stream's frame rate
    (fixed: it is part of the recording). ``step(betas, pose, trans)`` returns the frame's garment,
    a tensor the next call overwrites (clone it to keep it).
    """

    def __init__(self, model, fps: float, *, warmup: int = 3):
        from simgen.learn.garment_model import StreamState

        self.model, self.fps, self.warmup = model, float(fps), int(warmup)
        self.state = StreamState()
        self._started = False
        self.graph = None
        self._inputs: tuple[torch.Tensor, ...] = ()
        self._output: torch.Tensor | None = None

    @torch.no_grad()
    def step(self, betas: torch.Tensor, pose: torch.Tensor, trans: torch.Tensor) -> torch.Tensor:
        """The garment [m] (N, V, 3) of the next frame: betas (N, B), pose (N, 24, 3) [rad], trans (N, 3) [m]."""
        if betas.device.type != "cuda":
            raise InputError(f"a graphed stream runs on a CUDA device, got inputs on {betas.device}")
        if not self._started:  # the first frame: eager, no history
            self._started = True
            return self.model.step(self.state, betas, pose, trans, self.fps, postprocess=False)
        if self.graph is None:
            with torch.cuda.device(betas.device):    # capture on the stream's GPU, not the current one
                self._record(betas, pose, trans)
        for name, buf, x in zip(("betas", "pose", "trans"), self._inputs, (betas, pose, trans)):
            if x.shape != buf.shape:
                raise InputError(f"a graphed stream keeps the shapes it was recorded with: {name} has shape "
                                 f"{tuple(x.shape)}, the recording {tuple(buf.shape)} (start a new stream)")
        for buf, x in zip(self._inputs, (betas, pose, trans)):
            buf.copy_(x)
        with torch.cuda.device(betas.device):
            self.graph.replay()
        return self._output

    def _record(self, betas, pose, trans) -> None:
        """Record one frame that starts from the current state (recording runs nothing)."""
        from simgen.learn.garment_model import StreamState

        def copy(state):  # a state whose tensors are fresh copies (None stays None)
            prev = None if state.previous is None else tuple(x.clone() for x in state.previous)
            return StreamState(hidden=None if state.hidden is None else state.hidden.clone(), previous=prev)

        def tensors(state):
            return [x for x in (state.hidden, *(state.previous or ())) if x is not None]

        inputs = tuple(x.clone() for x in (betas, pose, trans))
        carried = copy(self.state)
        side = torch.cuda.Stream(device=betas.device)
        side.wait_stream(torch.cuda.current_stream(betas.device))
        with torch.cuda.stream(side):  # warm-up on a side stream (cuDNN and the allocator settle)
            for _ in range(self.warmup):
                self.model.step(copy(carried), *inputs, self.fps, postprocess=False)
        torch.cuda.current_stream(betas.device).wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            s = StreamState(hidden=carried.hidden, previous=carried.previous)
            out = self.model.step(s, *inputs, self.fps, postprocess=False)
            ends = tensors(s)
            if len(ends) != len(tensors(carried)):
                raise InputError("a graphed model's step must keep the shape of its stream state")
            for dst, src in zip(tensors(carried), ends):  # the next replay starts from here
                dst.copy_(src)
        self.graph, self._inputs, self._output, self.state = graph, inputs, out, carried
