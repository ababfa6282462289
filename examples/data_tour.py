#!/usr/bin/env python3
"""A tour of the data layer on generated episodes, with no server: messy input in, training windows out.

    .venv/bin/python examples/data_tour.py [--out DIR] [--steps 20000] [--train-steps 400] [--fresh] [--json]

Episodes in every shape a real robot fleet produces (clean canonical dirs at 10/20/50 Hz, a
camelCase XR-app dir, a gzip TFRecord, an MCAP, a file with a truncated last line, one with a NaN,
a metadata-only dir) are validated, ingested twice (the second run must change nothing), compiled
into the memory-mapped cache and cut into time-based windows by the resumable sampler; then the
three HOPE components are trained one after the other, each in its own process
(`train --sequential vqvae,fast_loop,mid_loop`), and the per-component results are printed.

`make demo` is the whole loop through the services (recording, training, promotion, inference);
this tour is the part before training, step by step, on the awkward inputs the services accept.
It runs from the checkout: it imports the repository's packages and starts `run_trainer.py`.
Exit 0 when every check held, 1 when one did not, 2 for bad arguments.
"""
from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402 (after the sys.path setup)

from hope_models.data.cache import load_or_build  # noqa: E402
from hope_models.data.sampler import AnchorSampler, split_episodes  # noqa: E402
from hope_models.data.summary import format_summary, summarise_dataset  # noqa: E402
from hope_models.data.synthetic import generate_dataset  # noqa: E402
from hope_models.data.windows import make_windows, window_spec  # noqa: E402
from hope_models.rlds.discover import read_path  # noqa: E402
from hope_models.rlds.ingest import ingest_paths  # noqa: E402
from hope_models.rlds.validation_report import validate_paths  # noqa: E402
from hope_models.rlds.write_mcap import write_episode_mcap  # noqa: E402
from hope_models.rlds.write_tfrecord import episode_to_examples, write_tfrecord  # noqa: E402
from hope_models.settings import SettingsError, load_settings  # noqa: E402

MIN_STEPS = 2_000  # the windows need whole 2 s spans: 200-step episodes at 10 Hz
TRUNCATE_AT = 300  # the truncated file keeps this many whole lines of an episode (fewer if it is shorter)
IMAGINED_RATIO = 0.1  # of each batch, when the train split has imagined episodes (a small dataset may not)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--out", metavar="DIR", help="where the tour writes (default: $HOPE_HOME/data_tour)")
    parser.add_argument("--steps", type=int, default=20_000,
                        help=f"synthetic steps to generate (default 20000, at least {MIN_STEPS})")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--train-steps", type=int, default=400,
                        help="training steps per component (default 400; 0 skips training)")
    parser.add_argument("--fresh", action="store_true", help="delete the tour's dir first")
    parser.add_argument("--json", action="store_true", help="print the final summary as JSON")
    return parser.parse_args(argv)


class Tour:
    """The tour's state: where it writes, what it prints, and the result it builds step by step."""

    def __init__(self, args: argparse.Namespace, out: Path):
        self.args, self.out = args, out
        self.raw, self.dataset, self.cache_root = out / "raw", out / "dataset", out / "cache"
        self.timings: dict[str, float] = {}
        self.result: dict[str, Any] = {"out": str(out)}

    def say(self, text: str) -> None:
        if not self.args.json:
            print(text, flush=True)

    def timed(self, name: str, t0: float) -> None:
        self.timings[name] = round(time.perf_counter() - t0, 2)


# -- 1. episodes, clean and messy ------------------------------------------------------------------

def _camel_case_episode(dst: Path, src_episode_dir: Path) -> None:
    """The XR app's way of writing the same episode: camelCase steps, dotted metadata keys."""
    steps_out = []
    for line in (src_episode_dir / "steps" / "000000.jsonl").read_text().splitlines()[:200]:
        s = json.loads(line)
        rs = s["observation"]["robot_state"]
        steps_out.append(json.dumps({
            "observation": {"robotState": {"timestampNanos": rs["timestamp_nanos"],
                                           "jointPositions": rs["joint_positions"],
                                           "jointVelocities": rs["joint_velocities"]}},
            "action": {"command": s["action"]["command"], "source": "human_teleop_xr"},
            "reward": s["reward"], "isTerminal": s["is_terminal"], "stepMetadata": {},
        }))
    (dst / "steps").mkdir(parents=True, exist_ok=True)
    (dst / "steps" / "000000.jsonl").write_text("\n".join(steps_out) + "\n", encoding="utf-8")
    (dst / "metadata.json").write_text(json.dumps({
        "continuon.xr_mode": "trainer", "continuon.control_role": "human_teleop",
        "environment_id": "demo-lab", "tags": ["demo", "xr_app"], "software": None,
    }), encoding="utf-8")


def make_messy_sources(raw: Path, clean: Path) -> dict[str, str]:
    """Write the awkward shapes next to the clean dirs; returns source name -> expected outcome.

    Each shape is made from one of the clean episodes, in turn; a small dataset (few episodes)
    reuses them, which is fine: every messy source gets its own episode id."""
    messy = raw / "messy"
    messy.mkdir(parents=True, exist_ok=True)
    sources = sorted(p for p in clean.iterdir() if p.is_dir())
    source = lambda i: sources[i % len(sources)]  # noqa: E731
    expected: dict[str, str] = {}

    _camel_case_episode(messy / "xr_app_camelcase", source(0))
    expected["xr_app_camelcase"] = "accepted (aliases mapped)"

    (ep,) = read_path(source(1))[0].episodes
    ep.episode_id = ep.metadata["episode_id"] = "converted_tfrecord"
    write_tfrecord(messy / "converted.tfrecord", episode_to_examples(ep), gzip=True)
    expected["converted.tfrecord"] = "accepted, warns that TFRecord carries no episode metadata"

    (ep,) = read_path(source(2))[0].episodes
    ep.episode_id = ep.metadata["episode_id"] = "exported_mcap"
    write_episode_mcap(ep, messy / "exported.mcap")
    expected["exported.mcap"] = "accepted (MCAP container)"

    lines = (source(3) / "steps" / "000000.jsonl").read_text().splitlines()
    keep = min(TRUNCATE_AT, len(lines) - 1)  # whole lines, then half of the next one
    (messy / "truncated.jsonl").write_text("\n".join(lines[:keep]) + "\n" + lines[keep][: len(lines[keep]) // 2],
                                           encoding="utf-8")
    expected["truncated.jsonl"] = "partly recovered (truncated last line dropped)"

    bad = lines[:50]
    bad[20] = bad[20].replace('"joint_positions":[', '"joint_positions":[NaN,', 1)
    (messy / "nan_token.jsonl").write_text("\n".join(bad) + "\n", encoding="utf-8")
    expected["nan_token.jsonl"] = "rejected (NaN, and a vector whose length changes)"

    (messy / "metadata_only").mkdir(exist_ok=True)
    (messy / "metadata_only" / "metadata.json").write_text('{"xr_mode": "autonomous"}', encoding="utf-8")
    expected["metadata_only"] = "skipped (no steps)"
    return expected


def generate(tour: Tour) -> None:
    t0 = time.perf_counter()
    if (tour.raw / "clean").exists():
        tour.say("1. episodes: reusing the ones generated earlier (use --fresh to regenerate)")
    else:
        g = generate_dataset(tour.raw / "clean", tour.args.steps, seed=tour.args.seed, imagined_fraction=0.1,
                             episode_seconds=(20.0, 40.0), id_prefix="demo")
        tour.say(f"1. generated {g.episodes} episodes ({g.imagined_episodes} imagined), {g.steps} steps "
                 f"at 10/20/50 Hz in {g.seconds:.1f} s")
        expected = make_messy_sources(tour.raw, tour.raw / "clean")
        tour.say("   plus the shapes real producers write:")
        for name, outcome in expected.items():
            tour.say(f"     messy/{name:<22} expected: {outcome}")
    tour.timed("generate", t0)


# -- 2-4. validate, ingest, cache ------------------------------------------------------------------

def validate(tour: Tour) -> None:
    t0 = time.perf_counter()
    report = validate_paths([tour.raw], profile="train")
    tour.timed("validate", t0)
    s = tour.result["validate"] = report["summary"]
    tour.say(f"\n2. validate --profile train: {s['episodes']} episodes, {s['steps']} steps: "
             f"{s['accepted']} accepted, {s['accepted_with_warnings']} with warnings, "
             f"{s['partly_recovered']} partly recovered, {s['rejected']} rejected, {s['skipped']} skipped")
    for e in report["episodes"]:
        if "/messy/" in e["source"] or e["status"] == "rejected":
            first = (e["errors"] or e["warnings"] or ["no findings"])[0]
            tour.say(f"     {e['status']:<22} {Path(e['source']).name}: {first.split(': ', 1)[-1][:100]}")


def ingest(tour: Tour) -> None:
    t0 = time.perf_counter()
    first = tour.result["ingest_first"] = ingest_paths([tour.raw], tour.dataset)["summary"]
    second = tour.result["ingest_second"] = ingest_paths([tour.raw], tour.dataset)["summary"]
    tour.timed("ingest", t0)
    tour.say(f"\n3. ingest -> {tour.dataset}: {first['written']} written, {first['unchanged']} unchanged, "
             f"{first['rejected']} rejected, {first['skipped']} skipped")
    tour.say(f"   ingest again: {second['written']} written, {second['unchanged']} unchanged "
             "(idempotent: same ids, nothing rewritten)")
    recheck = validate_paths([tour.dataset], profile="train")["summary"]
    tour.result["dataset_ok"] = recheck["ok"]
    tour.say(f"   validate the dataset: {'ok' if recheck['ok'] else 'NOT OK'} ({recheck['episodes']} episodes)")


def cache(tour: Tour) -> None:
    t0 = time.perf_counter()
    summary = summarise_dataset(tour.dataset, tour.cache_root)
    tour.timed("cache", t0)
    tour.say("\n4. dataset, feature spec and cache:\n   " + format_summary(summary).replace("\n", "\n   "))
    reused = tour.result["cache_reused_on_second_open"] = summarise_dataset(tour.dataset, tour.cache_root)["reused"]
    tour.say(f"   second open: cache {'reused' if reused else 'REBUILT (unexpected)'}")
    tour.result["dataset"] = {k: summary[k] for k in ("episodes", "steps", "imagined_episodes", "rates", "obs_dim",
                                                      "act_dim", "cache_path", "fingerprint")}


# -- 5. windows ------------------------------------------------------------------------------------

def windows(tour: Tour) -> None:
    t0 = time.perf_counter()
    data, _ = load_or_build(tour.dataset, tour.cache_root)
    has_imagined = bool(data.imagined[split_episodes(data, "train", 0.1)].any())
    mix = {"batch_size": 64, "min_history_s": 0.1, "imagined_ratio": IMAGINED_RATIO if has_imagined else 0.0}
    sampler = AnchorSampler(data, seed=tour.args.seed, **mix)
    fast, mid = window_spec("fast"), window_spec("mid", horizons_s=(1.0,))
    n_batches = 200
    for _ in range(n_batches):
        batch = make_windows(data, sampler.next_batch(), fast)
    fast_rate = n_batches / (time.perf_counter() - t0)
    resumed = AnchorSampler(data, seed=tour.args.seed, **mix)
    resumed.load_state_dict(sampler.state_dict())
    same = bool(np.array_equal(resumed.next_batch(), sampler.next_batch()))
    mid_batch = make_windows(data, sampler.next_batch(), mid)
    tour.timed("windows", t0)
    tour.result["fast_batches_per_s"] = round(fast_rate, 1)
    tour.result["sampler_resume_identical"] = same
    tour.say("\n5. windows (cut by time, resampled to a fixed grid):")
    tour.say(f"   fast {fast.duration_s * 1000:.0f} ms x {fast.k} points: obs {list(batch.obs.shape)}, "
             f"act {list(batch.act.shape)}, {fast_rate:.0f} batches/s of 64")
    tour.say(f"   mid {mid.duration_s:.0f} s x {mid.k} points + 1 s ahead: obs {list(mid_batch.obs.shape)}, "
             f"future {list(mid_batch.future_obs.shape)}, {int(mid_batch.mask.sum())} of "
             f"{mid_batch.mask.size} grid points inside their episodes")
    tour.say(f"   sampler resumed from its saved position draws the same next batch: {same}")


# -- 6. training -----------------------------------------------------------------------------------

def train(tour: Tour) -> None:
    """`run_trainer.py train --sequential ...` in a child process: this process never imports torch,
    and each component's memory goes back to the OS when its own process exits."""
    tour.result["training"] = []
    if tour.args.train_steps <= 0:
        return
    t0 = time.perf_counter()
    tour.say(f"\n6. training vqvae, fast_loop, mid_loop for {tour.args.train_steps} steps each, "
             "each in its own process (progress below):")
    cmd = [sys.executable, str(REPO / "run_trainer.py"), "train", "--sequential", "vqvae,fast_loop,mid_loop",
           "--data", str(tour.dataset), "--run-dir", str(tour.out / "runs"), "--steps", str(tour.args.train_steps),
           "--seed", str(tour.args.seed), "--cache-dir", str(tour.cache_root), "--json"]
    # the children's progress lines go to our stderr as they happen; the JSON table comes on stdout
    proc = subprocess.run(cmd, stdout=subprocess.PIPE, text=True)
    try:
        training = json.loads(proc.stdout.strip().splitlines()[-1])
    except (ValueError, IndexError):
        training = [{"component": "sequence", "outcome": "failed",
                     "message": f"train --sequential exited with code {proc.returncode} and no result"}]
    tour.timed("train", t0)
    tour.result["training"] = training
    if not tour.args.json:
        from hope_models.train.sequential import format_table
        print("   " + format_table(training).replace("\n", "\n   "))


def finish(tour: Tour, started: float) -> int:
    r = tour.result
    r["seconds"] = tour.timings
    r["total_seconds"] = round(time.perf_counter() - started, 1)
    training = r["training"]
    trained_ok = all(t.get("outcome") == "completed" for t in training) and (
        tour.args.train_steps <= 0 or len(training) == 3)
    r["ok"] = ok = (r["dataset_ok"] and r["ingest_second"]["written"] == 0 and r["cache_reused_on_second_open"]
                    and r["sampler_resume_identical"] and r["validate"]["rejected"] >= 1 and trained_ok)
    if tour.args.json:
        print(json.dumps(r, indent=1))
    else:
        for t in training:
            if t.get("outcome") != "completed":
                print(f"training {t['component']} did not complete: {t.get('message', t.get('outcome'))}")
        print(f"\nSummary: {r['dataset']['episodes']} episodes / {r['dataset']['steps']} steps ingested and cached; "
              f"{r['validate']['rejected']} rejected with reasons; re-ingest changed nothing; "
              f"total {r['total_seconds']:.1f} s. {'OK' if ok else 'SOMETHING IS WRONG (see above)'}")
    return 0 if ok else 1


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        settings = load_settings()
    except SettingsError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.steps < MIN_STEPS:
        print(f"error: --steps must be at least {MIN_STEPS} (the tour cuts 2 s windows from 200-step episodes)",
              file=sys.stderr)
        return 2
    out = Path(args.out).expanduser() if args.out else settings.home / "data_tour"
    if args.fresh and out.exists():
        shutil.rmtree(out)
    started = time.perf_counter()
    tour = Tour(args, out)
    tour.say(f"HOPE Seed Trainer data tour -> {out}\n")
    for step in (generate, validate, ingest, cache, windows, train):
        step(tour)
    return finish(tour, started)


if __name__ == "__main__":
    sys.exit(main())
