"""Frame-by-frame inference of the learned garment models, eager against a CUDA graph, as JSON.

For each method (SNUG's 4x256 GRU, the ch. 4 fit MLP + wrinkle GRU, LBS of the ch. 4 template),
one garment streamed over a held-out clip: ms per frame with every kernel launched from Python
(``time_inference``) and replayed from a recorded frame (``cuda_graph=True``,
:class:`simgen.learn.streaming.GraphedStream`), and the largest difference [m] between the two
streams' garments over the whole clip (the graph must reproduce the eager frames). For the
supervised model also with its post-processes: eagerly (the thesis's push; the metric one) and,
on CUDA, the network from the graph followed by the eager body and post-process. On CUDA the
metric post-process of one frame replays its iterations from CUDA graphs of its own (between its
body queries, :class:`simgen.learn.relax.MetricRelax`) in both.

    python scripts/bench_inference.py --device cuda --supervised runs/thesis/model [--snug runs/snug]

--snug: a ``train snug`` folder (default: SNUG trained for --snug-epochs epochs here: the runtime
does not depend on the weights). --supervised: a ``train fit|wrinkle`` folder; when its wrinkle/
holds a config.json but no weights (scripts/train_thesis.py returns it so, without its ~110 MB),
the wrinkle GRU of that config is built with fresh weights and the JSON says so.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _record import commit  # noqa: E402


def supervised_model(folder: Path, device):
    """(GarmentModel, note): the folder's model; a wrinkle GRU without weights gets fresh ones."""
    from simgen.learn.checkpoint import read_config
    from simgen.learn.garment_model import GarmentModel, load_garment_model
    from simgen.learn.models import WrinkleGRU

    if (folder / "wrinkle" / "model.pt").is_file() or not (folder / "wrinkle" / "config.json").is_file():
        return load_garment_model(folder, device=device), "trained weights"
    from simgen.learn.checkpoint import load_model
    from simgen.learn.data import body_for_identity

    template, fit = load_model(folder / "template"), load_model(folder / "fit")
    cfg = dict(read_config(folder / "wrinkle")["model"])
    wrinkle = WrinkleGRU(cfg.pop("num_betas"), cfg.pop("num_features"), cfg.pop("num_vertices"), **cfg).eval()
    model = GarmentModel(template, fit, wrinkle, body_for_identity({"body": template.saved_config["body"]}))
    return model.to(device), "wrinkle GRU with fresh weights (timing only; its config.json from the folder)"


def stream_difference(stepper, clip, device) -> float:
    """Largest |eager - graphed| [m] over a clip streamed both ways."""
    from simgen.learn.garment_model import StreamState
    from simgen.learn.streaming import GraphedStream

    b, p, t = (torch.as_tensor(x, dtype=torch.float32, device=device) for x in clip[:3])
    state, graphed, worst = StreamState(), GraphedStream(stepper, clip[3]), 0.0
    for i in range(len(p)):
        a = stepper.step(state, b[i:i + 1], p[i:i + 1], t[i:i + 1], clip[3], postprocess=False)
        g = graphed.step(b[i:i + 1], p[i:i + 1], t[i:i + 1])
        worst = max(worst, float((a - g).abs().max()))
    return worst


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--supervised", type=Path, required=True)
    ap.add_argument("--snug", type=Path)
    ap.add_argument("--snug-epochs", type=int, default=1)
    ap.add_argument("--clip", default="walk_fast")
    ap.add_argument("--frames", type=int, default=200)
    a = ap.parse_args()
    from simgen.learn.comparison.metrics import LbsStepper, SnugStepper
    from simgen.learn.evaluate import time_inference
    from simgen.learn.snug import SnugConfig, load_snug_model, train_snug
    from simgen.motion import load_motion

    dev = torch.device(a.device)
    sup, note = supervised_model(a.supervised, dev)
    if a.snug is None:
        a.snug = Path(tempfile.mkdtemp()) / "snug"
        train_snug(sup.template.saved_config["garment"]["name"], a.snug, device=a.device,
                   config=SnugConfig(epochs=a.snug_epochs))
    snug = load_snug_model(a.snug, device=dev)
    motion = load_motion(a.clip)
    betas = np.zeros((len(motion.poses), sup.fit.num_betas), dtype=np.float32)
    clip = (betas, motion.poses.astype(np.float32), motion.trans.astype(np.float32), float(motion.fps))
    methods = {"snug": SnugStepper(snug), "supervised": sup, "lbs": LbsStepper(sup.template, sup.body)}
    rows = {}
    for name, stepper in methods.items():
        rows[name] = {mode: time_inference(stepper, *clip[:3], clip[3], device=dev, postprocess=False,
                                           frames=a.frames, cuda_graph=graph)
                      for mode, graph in (("eager", False), ("cuda_graph", True))}
        rows[name]["speedup"] = rows[name]["eager"]["mean_ms"] / rows[name]["cuda_graph"]["mean_ms"]
        rows[name]["max_difference_m"] = stream_difference(stepper, clip, dev)
    rows["supervised"]["with_postprocess_eager"] = time_inference(sup, *clip[:3], clip[3], device=dev,
                                                                  postprocess=True, frames=a.frames)
    rows["supervised"]["with_metric_postprocess_eager"] = time_inference(sup, *clip[:3], clip[3], device=dev,
                                                                         postprocess=True, relax=True,
                                                                         frames=a.frames)
    if dev.type == "cuda":
        for kind in ("push", "metric"):
            rows["supervised"][f"cuda_graph_then_{kind}"] = time_inference(
                sup, *clip[:3], clip[3], device=dev, postprocess=True, relax=kind == "metric", frames=a.frames,
                cuda_graph=True)
    print(json.dumps({"device": torch.cuda.get_device_name(dev) if dev.type == "cuda" else "cpu",
                      "commit": commit(), "torch": torch.__version__, "clip": a.clip, "frames": a.frames,
                      "garment_vertices": int(sup.fit.num_vertices), "supervised_weights": note,
                      "methods": rows}, indent=1))


if __name__ == "__main__":
    main()
