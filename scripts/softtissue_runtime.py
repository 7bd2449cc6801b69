"""SoftSMPL's runtime per frame (thesis section 3.5: 4.8 ms with TensorRT on a GTX 1080), played one
frame at a time as an avatar would and as a whole clip at once, with the pose encoder's and the
soft-tissue decoder's share; prints (and saves) JSON with device, commit and sizes.

    python scripts/softtissue_runtime.py --devices cuda,cpu               # the default sizes
    python scripts/softtissue_runtime.py --model runs/st/full --devices cuda

Without --model, a SoftSMPL of the default sizes on the bundled open body is trained for one epoch
per stage on the synthetic test signal: the timing depends on the sizes, not on the weights. The
clip played is the library's ``--motion`` at beta = 0.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from dataset_bench import _commit, _cpu_name, _emit  # noqa: E402  (one definition of what a benchmark records)


def _machine(devices: list[str]) -> dict:
    import torch

    info = {"torch": torch.__version__, "python": platform.python_version(), "cpus": os.cpu_count(),
            "torch_threads": torch.get_num_threads(), "cpu": _cpu_name()}
    if any(d.startswith("cuda") for d in devices):
        info["gpu"] = torch.cuda.get_device_name(0)
    return info


def _part_ms(fn, sync, repeats: int = 200) -> float:
    """Milliseconds per call of ``fn``, each waited for."""
    import torch

    with torch.no_grad():
        fn()
        sync()
        t0 = time.perf_counter()
        for _ in range(repeats):
            fn()
            sync()
    return 1e3 * (time.perf_counter() - t0) / repeats


def _default_model(device: str) -> str:
    from simgen.body import load
    from simgen.learn.softtissue.data import synthetic_softtissue_data
    from simgen.learn.softtissue.train import SoftTissueConfig, train_softtissue

    body = load("open")
    data = synthetic_softtissue_data(body, motions=("walk", "run"), subjects=2, frames=60)
    folder = tempfile.mkdtemp(prefix="simgen-strt-")
    train_softtissue(data, folder, body=body, device=device,
                     config=SoftTissueConfig(pose_epochs=1, ae_epochs=1, reg_epochs=1, test_motions="run"))
    return folder


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", help="a trained SoftSMPL folder (default: the default sizes, see above)")
    p.add_argument("--devices", default="cpu", help="comma-separated torch devices, e.g. cuda,cpu")
    p.add_argument("--motion", default="walk", help="library clip to play")
    p.add_argument("--frames", type=int, default=240)
    p.add_argument("--repeats", type=int, default=2, help="timed plays per device")
    p.add_argument("--out", help="also write the JSON to this file")
    a = p.parse_args(argv)

    import numpy as np
    import torch

    from simgen.learn.softtissue.evaluate import softtissue_runtime
    from simgen.learn.softtissue.train import load_softtissue_model
    from simgen.motion import load_motion

    devices = [d.strip() for d in a.devices.split(",") if d.strip()]
    folder = a.model or _default_model(devices[0])
    clip = load_motion(a.motion)
    n = min(a.frames, len(clip.poses))

    class _Clip:  # what softtissue_runtime plays
        betas, fps, num_frames = np.zeros(10, np.float32), clip.fps, n
        poses, trans = clip.poses[:n].reshape(n, 72), clip.trans[:n]

    result = {"benchmark": "softtissue_runtime", "date": time.strftime("%Y-%m-%d"), "commit": _commit(),
              "machine": _machine(devices), "model": a.model or "default sizes (one epoch on the synthetic signal)",
              "motion": a.motion, "frames": n, "thesis_ms_per_frame": 4.8, "devices": {}}
    for dev in devices:
        model = load_softtissue_model(folder, device=dev)
        sync = torch.cuda.synchronize if dev.startswith("cuda") else (lambda: None)
        runs = [softtissue_runtime(model, _Clip, n) for _ in range(a.repeats)]
        pose = torch.as_tensor(_Clip.poses[:1], dtype=torch.float32, device=dev)
        code = torch.zeros(model.regressor.latent, device=dev)
        result["devices"][dev] = {
            "streamed_ms_per_frame": [r["ms_per_frame"] for r in runs],
            "sequence_ms_per_frame": [r["sequence_ms_per_frame"] for r in runs],
            "pose_encoder_ms": _part_ms(lambda: model.pose_ae.encode_pose(pose[:, 3:]), sync),
            "decoder_ms": _part_ms(lambda: model.soft_ae.decode(code), sync),
            "parameters": runs[0]["parameters"], "megabytes_float32": runs[0]["megabytes_float32"]}
    _emit(result, a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
