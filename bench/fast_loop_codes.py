"""Fast Loop training speed on camera frames (through the frozen tokenizer's code table) against the
same Fast Loop on the joints alone ("joints": the observation vector, no frame): steps/s of the
real `train` command, alternating rounds in one run so the shared machine's noise falls on both.
Target: frames >= 80 % of joints. "state" is the Fast Loop on the vector observation as `make demo`
trains it (joints + target_offset, the codes of a vector VQ-VAE; 50 state demos of the same seeds
recorded by the bench, their VQ-VAE trained 200 steps: its speed does not depend on how well).
"frames" is the default policy (its keypoints also learn by
drawing the cells' code vectors back); "frames_reading" the same with keypoint_reader "policy"
(reading the codes alone, no drawing), which says what the drawing costs; "frames_drawing_codes"
the earlier drawing (each cell's code as one of n_codes classes).

    .venv/bin/python bench/fast_loop_codes.py --data DS --vqvae VQ_RUN [--steps 400 --rounds 3]

DS is a camera dataset (sim-demos --observation camera), VQ_RUN a frame VQ-VAE trained on it (its
code table is built once, before the first timed round). Steps/s are read from each run's
metrics.jsonl between step --warm and the last step (setup, cache and code-table building and the
end-of-job validation excluded). It prints figures (JSON); it is not a test.
"""
from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def steps_per_s(run_dir: Path, warm: int) -> float:
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    points = [(r["step"], r["wall_time"]) for r in rows if r.get("type") == "metric" and "steps_per_s" in r]
    timed = [p for p in points if p[0] >= warm]
    if len(timed) < 2:
        raise RuntimeError(f"{run_dir}: fewer than two progress points after step {warm}")
    (s0, t0), (s1, t1) = timed[0], timed[-1]
    return (s1 - s0) / (t1 - t0)


def train(data: Path, cache: Path, run_dir: Path, steps: int, threads: int, vqvae: Path | None,
          model_config: dict | None = None) -> None:
    cmd = [sys.executable, "run_trainer.py", "train", "--component", "fast_loop", "--data", str(data),
           "--cache-dir", str(cache), "--run-dir", str(run_dir), "--steps", str(steps), "--threads", str(threads),
           "--log-every", "10", "--checkpoint-every", str(steps)]
    if vqvae is not None:
        cmd += ["--vqvae", str(vqvae)]
    if model_config:
        cmd += ["--model-config", json.dumps(model_config)]
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{proc.stderr[-2000:]}")


def state_recipe(root: Path, episodes: int, threads: int) -> tuple[Path, Path]:
    """The vector recipe's data and tokenizer: state demos (no frames) and a vector VQ-VAE on them."""
    data, vq = root / "state", root / "state_vq"
    for cmd in (["sim-demos", "--episodes", str(episodes), "--out", str(data)],
                ["train", "--component", "vqvae", "--data", str(data), "--cache-dir", str(root / "state_cache"),
                 "--run-dir", str(vq), "--steps", "200", "--threads", str(threads)]):
        proc = subprocess.run([sys.executable, "run_trainer.py", *cmd], cwd=REPO, capture_output=True, text=True)
        if proc.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed:\n{proc.stderr[-2000:]}")
    return data, vq


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--vqvae", type=Path, required=True)
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--warm", type=int, default=50)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--state-episodes", type=int, default=50, help="state demos the vector recipe trains on")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="flcodes-") as tmp:
        root = Path(tmp)
        cache = root / "cache"
        train(args.data, cache, root / "prime", 20, args.threads, args.vqvae)  # cache + code table, untimed
        state_data, state_vq = state_recipe(root, args.state_episodes, args.threads)
        train(state_data, root / "state_cache", root / "state_prime", 20, args.threads, state_vq)
        variants = (("joints", None, None), ("state", state_vq, None), ("frames", args.vqvae, None),
                    ("frames_reading", args.vqvae, {"keypoint_reader": "policy"}),
                    ("frames_drawing_codes", args.vqvae, {"keypoint_draw": "codes"}))
        rates: dict[str, list[float]] = {name: [] for name, _, _ in variants}
        for r in range(args.rounds):
            for name, vq, mc in variants:
                run = root / f"{name}-{r}"
                if name == "state":
                    train(state_data, root / "state_cache", run, args.steps, args.threads, vq, mc)
                else:
                    train(args.data, cache, run, args.steps, args.threads, vq, mc)
                rates[name].append(steps_per_s(run, args.warm))
    med = {k: statistics.median(v) for k, v in rates.items()}
    print(json.dumps({"steps_per_s": rates, "median": med, "frames_over_joints": med["frames"] / med["joints"],
                      "frames_over_state": med["frames"] / med["state"],
                      "frames_reading_over_joints": med["frames_reading"] / med["joints"],
                      "frames_drawing_codes_over_joints": med["frames_drawing_codes"] / med["joints"],
                      "target": 0.8, "steps": args.steps, "threads": args.threads}, indent=1))


if __name__ == "__main__":
    main()
