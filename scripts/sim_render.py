"""Turn the .npz files written by scripts/sim_library.py into USD + MP4 (CPU machine: usd-core, VTK).

    python scripts/sim_render.py runs/tshirt_walk.npz runs/tshirt_run.npz --out renders/
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("files", nargs="+", type=Path)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--no-video", action="store_true")
    args = parser.parse_args()

    from simgen.body import load
    from simgen.io.render import render_sequence, scene_legend
    from simgen.io.usd import MeshTrack, write_usd
    from simgen.motion import load_motion

    body = load("open")

    args.out.mkdir(parents=True, exist_ok=True)
    for path in args.files:
        with np.load(path) as data:
            garment = data["positions"].astype(np.float32)
            faces, fps, motion = data["faces"], float(data["fps"]), str(data["motion"])
            garment_name = json.loads(str(data["summary"])).get("garment") if "summary" in data else None
        clip = load_motion(motion)  # output frame k is the clip's frame k (mean shape)
        frames = garment.shape[0]
        posed = body.forward_sequence(np.zeros(1), clip.poses[:frames], clip.trans[:frames]).vertices
        tracks = [MeshTrack("body", posed, body.faces, role="body"),
                  MeshTrack("garment", garment, faces, role="garment")]
        print(write_usd(args.out / f"{path.stem}.usdc", tracks, fps=fps))
        if not args.no_video:
            legend = scene_legend(garment=garment_name, motion=motion)
            print(render_sequence(args.out / f"{path.stem}.mp4", tracks, fps=fps, legend=legend))


if __name__ == "__main__":
    main()
