"""Imagination from a learned world model: the acceptance pipeline of `imagine --method model`, and
the world model's error against horizon.

    .venv/bin/python bench/imagination.py                       # --play 20 --imagined 50 --wm-steps 3000
    .venv/bin/python bench/imagination.py --play 0,5,20,50      # one pipeline per play count
    .venv/bin/python bench/imagination.py --work W --keep       # keep the scratch dir

For each play count P (the simulator is used to record and to score, never to imagine):

1. `sim-demos --episodes 5 --noise 1.0` (expert demos, seeds 100000..), `sim-demos --policy play
   --episodes P` (unlabeled play, same seeds), `ingest` both into one dataset.
2. `train --sequential vqvae,mid_loop --steps N`: the VQ-VAE, then the Mid Loop and its world model.
3. `imagine --method model --model W/wm --demos W/demos --play W/play --episodes 50`: CEM in the
   world model from recorded start states (no simulator in that process).
4. `ingest` the imagined episodes into the dataset, `train --component fast_loop --imagined-ratio 0.5
   --steps 2000` (the same recipe as bench/reflex_imagined.py), `eval-reflex --episodes 20 --seed 0`
   (held-out seeds 0..19).

The world model's error: on 5 play episodes recorded at seeds 300000.. (never trained on), at 200
random anchors, the squared error per observation dim (normalised units) of the world model's
prediction after each held grid step, given the actions actually held at the grid points, against
copying the current observation. Prints a table (with --json one JSON object). Not a test.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

import reflex_imagined  # noqa: E402


def sh(cmd: list[str], log: list[str], quiet: bool) -> dict:
    """reflex_imagined.sh (run_trainer.py <cmd> --json), for ingest too, whose --json is one
    indented document rather than one line."""
    if cmd[0] not in ("ingest", "train"):
        return reflex_imagined.sh(cmd, log, quiet)
    import subprocess

    log.append("python run_trainer.py " + " ".join(cmd))
    if not quiet:
        print(f"$ {log[-1]}", file=sys.stderr, flush=True)
    proc = subprocess.run([sys.executable, str(REPO / "run_trainer.py"), *cmd, "--json"], capture_output=True,
                          text=True, cwd=REPO)
    if proc.returncode != 0:
        raise SystemExit(f"failed (exit {proc.returncode}): {log[-1]}\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}")
    if cmd[0] == "ingest":
        return json.loads(proc.stdout)
    out = json.loads(proc.stdout.strip().splitlines()[-1])  # train --sequential: a list, one per member
    return {"members": out} if isinstance(out, list) else out


def once(path: Path, cmd: list[str], log: list[str], quiet: bool) -> dict | None:
    """Run cmd unless path exists (a re-run with --work continues where the last one stopped)."""
    if path.exists():
        log.append("(kept) python run_trainer.py " + " ".join(cmd))
        return None
    return sh(cmd, log, quiet)


def model_error(model: Path, episodes: Path, anchors: int = 200, seed: int = 0) -> dict:
    """Per horizon (grid steps) and dim: the world model's MSE and copy-last's, normalised units."""
    import torch

    from hope_models.imagine.planner import WorldModel
    from hope_models.imagine.recorded import grid_history, read_recorded

    torch.set_num_threads(1)
    wm = WorldModel.load(model)
    eps = read_recorded([episodes], wm.spec)
    m = wm.model.cfg.wm_horizon
    rng = np.random.default_rng(seed)
    sub = int(round(wm.grid_s / float(np.median(np.diff(eps[0].t)))))
    rows = []
    for _ in range(anchors):
        e = eps[int(rng.integers(len(eps)))]
        s = int(rng.integers(0, len(e.t) - m * sub - 1))
        h_obs, h_act, h_mask = grid_history(e, s, wm.k, wm.grid_s)
        fut = [s + (j + 1) * sub for j in range(m)]
        acts = np.stack([e.act[s + j * sub] for j in range(m)])  # held at each grid point
        rows.append((h_obs, h_act, h_mask, e.obs[fut], acts))
    h_obs, h_act, h_mask, target, acts = (np.stack([r[i] for r in rows]) for i in range(5))
    y = wm.context(h_obs, h_act, h_mask)
    pred = wm.predict(y, h_obs[:, -1], acts).numpy()
    err = ((pred - target) ** 2).mean(0)  # [M, D]
    copy = ((h_obs[:, -1:, :] - target) ** 2).mean(0)
    names = wm.spec.observation.dim_names()
    return {"grid_step_s": wm.grid_s, "dims": names,
            "horizons_s": [round((j + 1) * wm.grid_s, 3) for j in range(m)],
            "mse": err.round(4).tolist(), "copy_mse": copy.round(4).tolist(),
            "mse_mean": err.mean(1).round(4).tolist(), "copy_mse_mean": copy.mean(1).round(4).tolist()}


def pipeline(work: Path, play: int, args, log: list[str]) -> dict:
    q = args.quiet
    d = work / f"play{play}"
    once(d / "demos", ["sim-demos", "--episodes", str(args.demos), "--task", "reach", "--noise", "1.0",
                       "--out", str(d / "demos")], log, q)
    srcs = [str(d / "demos")]
    if play:
        once(d / "play", ["sim-demos", "--episodes", str(play), "--task", "reach", "--policy", "play",
                          "--out", str(d / "play")], log, q)
        srcs.append(str(d / "play"))
    once(d / "ds", ["ingest", *srcs, "--into", str(d / "ds")], log, q)
    t0 = time.perf_counter()
    once(d / "wm" / "mid_loop" / "result.json", ["train", "--sequential", "vqvae,mid_loop", "--data", str(d / "ds"),
                                                 "--run-dir", str(d / "wm"), "--steps", str(args.wm_steps)], log, q)
    wm_s = sum(json.loads((d / "wm" / c / "result.json").read_text()).get("elapsed_s", 0.0)
               for c in ("vqvae", "mid_loop")) or time.perf_counter() - t0  # the first run's, on a re-run
    imag = ["imagine", "--method", "model", "--model", str(d / "wm"), "--demos", str(d / "demos"),
            "--episodes", str(args.imagined), "--out", str(d / "imagined")]
    if play:
        imag += ["--play", str(d / "play")]
    im = once(d / "imagined", imag + [*args.imagine_args], log, q)
    if im is not None:
        (d / "imagine.json").write_text(json.dumps(im))
        sh(["ingest", str(d / "imagined"), "--into", str(d / "ds")], log, q)
    im = json.loads((d / "imagine.json").read_text())
    once(d / "fast" / "result.json", ["train", "--component", "fast_loop", "--data", str(d / "ds"), "--run-dir",
                                      str(d / "fast"), "--steps", str(args.fast_steps), "--seed", "0",
                                      "--imagined-ratio", "0.5"], log, q)
    ev = sh(["eval-reflex", "--checkpoint", str(d / "fast"), "--episodes", "20", "--seed", "0", "--task", "reach"], log, q)
    return {"play": play, "mean_return": ev["mean_return"], "success_rate": ev["success_rate"],
            "time_to_reach_s": ev["time_to_reach_s"], "expert_mean_return": ev["expert_mean_return"],
            "wm_train_s": round(wm_s, 1), "imagine_s": im["_wall_s"],
            "imagined_final_goal_distance": im["mean_final_goal_distance"], "run": str(d)}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--play", default="20", help="comma-separated play-episode counts (default 20)")
    p.add_argument("--demos", type=int, default=5)
    p.add_argument("--imagined", type=int, default=50)
    p.add_argument("--wm-steps", type=int, default=3000, help="N of train --sequential vqvae,mid_loop")
    p.add_argument("--fast-steps", type=int, default=2000)
    p.add_argument("--imagine-args", nargs=argparse.REMAINDER, default=[], help="passed on to imagine")
    p.add_argument("--work", type=Path, default=None)
    p.add_argument("--keep", action="store_true")
    p.add_argument("--quiet", action="store_true")
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="imagination-"))
    log: list[str] = []
    out = {"runs": [], "commands": log}
    try:
        held = work / "heldout_play"
        if not held.exists():
            sh(["sim-demos", "--episodes", "5", "--task", "reach", "--policy", "play", "--seed", "300000",
                "--out", str(held)], log, args.quiet)
        for play in [int(x) for x in args.play.split(",")]:
            run = pipeline(work, play, args, log)
            run["model_error"] = model_error(Path(run["run"]) / "wm", held)
            out["runs"].append(run)
            if not args.json:
                _print_run(run)
    finally:
        if not args.keep and args.work is None:
            shutil.rmtree(work, ignore_errors=True)
    if args.json:
        print(json.dumps(out))
    return 0


def _print_run(run: dict) -> None:
    e = run["model_error"]
    print(f"play {run['play']}: mean return {run['mean_return']:.1f} (success {run['success_rate']:.0%}, expert "
          f"{run['expert_mean_return']:.1f}); world model {run['wm_train_s']:.0f} s, imagine {run['imagine_s']:.0f} s")
    print("  horizon  model mse  copy-last mse   " + "  ".join(d.split(".")[-1] for d in e["dims"]))
    for j, h in enumerate(e["horizons_s"]):
        print(f"  {h:5.1f} s  {e['mse_mean'][j]:9.4f}  {e['copy_mse_mean'][j]:13.4f}   "
              + "  ".join(f"{v:.4f}" for v in e["mse"][j]))


if __name__ == "__main__":
    raise SystemExit(main())
