"""Thesis ch. 5 on one GPU machine: SNUG to convergence, its ablations, the vertex-L2 GRU, the
ch. 4 supervised model on a store made beside them, and ``simgen eval compare`` on the held-out
sequences -- each piece a ``simgen`` command or ``scripts/train_thesis.py``, run side by side where
they do not compete for what is measured.

Schedule (each line starts when the one it names has ended):

1. at once: ``train snug`` (the full model, to convergence or ``--snug-budget`` s) and
   ``train_thesis.py`` (the ch. 4 store, fit + wrinkle training and its own evaluation);
2. after train_thesis: ``train gru-l2`` on its store, with its held-out shapes;
3. after SNUG: the five ablations and the full model for ``--ablation-epochs`` epochs, side by side
   (so each gets the same share of the GPU: the fixed budget of thesis Table 5.2);
4. after all of them: ``eval compare`` on at most ``--max-sequences`` sequences per held-out group.

Each finished run's log.csv and config.json are copied into --out at once, so a machine taken
back mid-run still returns them; times.json records when each piece started and ended. Models,
the store and compare.usdc stay in --work (a device call returns small files only); the MP4 is
rendered on a machine with OpenGL from --out/compare/compare_clips.npz (``simgen eval
compare-video``).

    # on the device machine, in the background (a call lasts at most 10 minutes):
    python scripts/compare_thesis.py --out runs/ch5 --work runs/ch5-work --device cuda
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

ABLATIONS = ("bending", "strain", "gravity", "inertia", "collision")
ROOT = Path(__file__).resolve().parent.parent


class Runner:
    """Starts commands in the background, logs each to OUT/<name>.log, records times in OUT/times.json."""

    def __init__(self, out: Path):
        self.out, self.t0, self.times, self.procs = out, time.monotonic(), {}, {}

    def start(self, name: str, argv: list[str]) -> None:
        log = open(self.out / f"{name}.log", "w")
        self.procs[name] = (subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT), log)
        self.times[name] = {"start_s": round(time.monotonic() - self.t0, 1)}
        self._save()

    def wait(self, *names: str, watch: tuple = ()) -> None:
        """Until every command in ``names`` has ended, recording the end of each (and of those in
        ``watch``, which are not waited for) as it comes. A command in ``names`` that failed stops
        the others and the script, naming its log (what later steps need is missing)."""
        while any("rc" not in self.times[n] for n in names):
            for name in (*names, *watch):
                proc, log = self.procs[name]
                if "rc" not in self.times[name] and proc.poll() is not None:
                    log.close()
                    self.times[name].update(end_s=round(time.monotonic() - self.t0, 1), rc=proc.returncode)
                    self._save()
            time.sleep(0.5)
        failed = [n for n in names if self.times[n]["rc"] != 0]
        if failed:
            for proc, _ in self.procs.values():
                if proc.poll() is None:
                    proc.terminate()
            sys.exit(f"compare_thesis: {failed[0]} failed (exit code {self.times[failed[0]]['rc']}); its output is "
                     f"in {self.out / (failed[0] + '.log')}")

    def _save(self) -> None:
        (self.out / "times.json").write_text(json.dumps(self.times, indent=1) + "\n")


def simgen(*args: str) -> list[str]:
    return [sys.executable, "-c", "import sys; from simgen.cli import main; main(sys.argv[1:])", *args]


def keep_logs(model: Path, out: Path) -> None:
    """Copy a model folder's log.csv and config.json (SNUG-type: model/snug/) into OUT/models/<name>/."""
    dst = out / "models" / model.name
    dst.mkdir(parents=True, exist_ok=True)
    for f in ("snug/log.csv", "snug/config.json", "split.json"):
        if (model / f).is_file():
            shutil.copy(model / f, dst / Path(f).name)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True, help="small files that come back")
    ap.add_argument("--work", type=Path, required=True, help="models and the store (stay)")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--garment", default="tshirt")
    ap.add_argument("--snug-budget", type=float, default=720.0, help="[s] of the full SNUG run")
    ap.add_argument("--ablation-epochs", type=int, default=12)
    ap.add_argument("--thesis-budget", type=float, default=560.0, help="[s] train_thesis.py's --total-budget")
    ap.add_argument("--l2-budget", type=float, default=180.0)
    ap.add_argument("--max-sequences", type=int, default=8, help="held-out sequences per group compared")
    ap.add_argument("--inside-stride", type=int, default=3)
    ap.add_argument("--snug-args", default="", help="more arguments of every `train snug`, e.g. '--motions walk'")
    ap.add_argument("--thesis-args", default="", help="more arguments of train_thesis.py, e.g. '--spec tiny'")
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    a.work.mkdir(parents=True, exist_ok=True)
    models, thesis = a.work / "models", a.work / "thesis"
    run = Runner(a.out)
    dev = ["--device", a.device]
    more = a.snug_args.split()
    run.start("snug", simgen("train", "snug", "--garment", a.garment, "--out", str(models / "snug"), *dev,
                             "--time-budget", str(a.snug_budget), *more))
    run.start("thesis", [sys.executable, "scripts/train_thesis.py", "--out", str(a.out / "thesis"), "--work",
                         str(thesis), *dev, "--total-budget", str(a.thesis_budget), *a.thesis_args.split()])
    run.wait("thesis", watch=("snug",))
    split = json.loads((thesis / "model" / "split.json").read_text())
    shapes = ",".join(split["test_shapes"])
    run.start("l2", simgen("train", "gru-l2", "--dataset", str(thesis / "dataset"), "--out", str(models / "l2"),
                           *dev, "--split", "shape", "--test-shapes", shapes, "--val-motions", "2",
                           "--time-budget", str(a.l2_budget)))
    run.wait("snug", watch=("l2",))
    keep_logs(models / "snug", a.out)
    fixed = ["--epochs", str(a.ablation_epochs)]
    names = [f"snug_no_{t}" for t in ABLATIONS] + [f"snug_e{a.ablation_epochs}"]
    for t, name in zip(ABLATIONS + (None,), names):
        run.start(name, simgen("train", "snug", "--garment", a.garment, "--out", str(models / name), *dev, *fixed,
                               *([f"--no-{t}"] if t else []), *more))
    run.wait("l2", *names)
    for name in ["l2", *names]:
        keep_logs(models / name, a.out)
    folders = [str(models / n) for n in ["snug", *names, "l2"]] + [str(thesis / "model")]
    run.start("compare", simgen("eval", "compare", "--models", *folders, "--dataset", str(thesis / "dataset"),
                                "--out", str(a.out / "compare"), "--test-shapes", shapes, *dev, "--no-video",
                                "--max-sequences", str(a.max_sequences), "--inside-stride", str(a.inside_stride)))
    run.wait("compare")
    for usd in (a.out / "compare").glob("*.usdc"):  # hundreds of MB: it stays with the models
        shutil.move(str(usd), a.work / usd.name)
    print(json.dumps({"commit": os.environ.get("SIMGEN_COMMIT", "unknown"), "times": run.times}))


if __name__ == "__main__":
    main()
