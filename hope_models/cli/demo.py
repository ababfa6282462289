"""`run_trainer.py demo`: the end-to-end job on generated episodes, with no server.

Episodes in every shape a real robot fleet produces (clean canonical dirs at 10/20/50 Hz, a
camelCase XR-app dir, a gzip TFRecord, an MCAP, a file with a truncated last line, one with a NaN,
a metadata-only dir) are validated, ingested twice (the second run must change nothing), compiled
into the memory-mapped cache and cut into time-based windows by the resumable sampler; then the
three HOPE components are trained one after the other, each in its own process
(`train --sequential vqvae,fast_loop,mid_loop`), and the per-component results are printed.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path
from typing import Any


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", metavar="DIR", help="where the demo writes (default: $HOPE_HOME/demo)")
    parser.add_argument("--steps", type=int, default=20_000, help="synthetic steps to generate (default 20000)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--train-steps", type=int, default=400,
                        help="training steps per component (default 400; 0 skips training)")
    parser.add_argument("--fresh", action="store_true", help="delete the demo dir first")
    parser.add_argument("--json", action="store_true", help="print the final summary as JSON")


def _say(args: argparse.Namespace, text: str) -> None:
    if not args.json:
        print(text, flush=True)


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
    """Write the awkward shapes next to the clean dirs; returns source name -> expected outcome."""
    from hope_models.rlds.discover import read_path
    from hope_models.rlds.write_mcap import write_episode_mcap
    from hope_models.rlds.write_tfrecord import episode_to_examples, write_tfrecord

    messy = raw / "messy"
    messy.mkdir(parents=True, exist_ok=True)
    sources = sorted(p for p in clean.iterdir() if p.is_dir())
    expected: dict[str, str] = {}

    _camel_case_episode(messy / "xr_app_camelcase", sources[0])
    expected["xr_app_camelcase"] = "accepted (aliases mapped)"

    (ep,) = read_path(sources[1])[0].episodes
    ep.episode_id = ep.metadata["episode_id"] = "converted_tfrecord"
    write_tfrecord(messy / "converted.tfrecord", episode_to_examples(ep), gzip=True)
    expected["converted.tfrecord"] = "accepted, warns that TFRecord carries no episode metadata"

    (ep,) = read_path(sources[2])[0].episodes
    ep.episode_id = ep.metadata["episode_id"] = "exported_mcap"
    write_episode_mcap(ep, messy / "exported.mcap")
    expected["exported.mcap"] = "accepted (MCAP container)"

    lines = (sources[3] / "steps" / "000000.jsonl").read_text().splitlines()
    (messy / "truncated.jsonl").write_text("\n".join(lines[:300]) + "\n" + lines[300][: len(lines[300]) // 2],
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


def _train_sequence(args: argparse.Namespace, dataset: Path, cache_root: Path, runs: Path) -> list[dict[str, Any]]:
    """`run_trainer.py train --sequential ...` in a child process: this process never imports torch,
    and each component's memory goes back to the OS when its own process exits."""
    import subprocess

    cmd = [sys.executable, str(Path(__file__).resolve().parents[2] / "run_trainer.py"), "train",
           "--sequential", "vqvae,fast_loop,mid_loop", "--data", str(dataset), "--run-dir", str(runs),
           "--steps", str(args.train_steps), "--seed", str(args.seed), "--cache-dir", str(cache_root), "--json"]
    # the children's progress lines go to our stderr as they happen; the JSON table comes on stdout
    proc = subprocess.run(cmd, stdout=subprocess.PIPE, text=True)
    try:
        return json.loads(proc.stdout.strip().splitlines()[-1])
    except (ValueError, IndexError):
        return [{"component": "sequence", "outcome": "failed",
                 "message": f"train --sequential exited with code {proc.returncode} and no result"}]


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from hope_models.data.cache import load_or_build
    from hope_models.data.sampler import AnchorSampler
    from hope_models.data.summary import format_summary, summarise_dataset
    from hope_models.data.synthetic import generate_dataset
    from hope_models.data.windows import make_windows, window_spec
    from hope_models.rlds.ingest import ingest_paths
    from hope_models.rlds.validation_report import validate_paths
    from hope_models.settings import SettingsError, load_settings

    try:
        settings = load_settings()
    except SettingsError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.steps < 2_000:
        print("error: --steps must be at least 2000 (the demo cuts 2 s windows from 200-step episodes)",
              file=sys.stderr)
        return 2
    out = Path(args.out).expanduser() if args.out else settings.home / "demo"
    if args.fresh and out.exists():
        shutil.rmtree(out)
    raw, dataset, cache_root = out / "raw", out / "dataset", out / "cache"
    started = time.perf_counter()
    timings: dict[str, float] = {}

    def timed(name: str, t0: float) -> None:
        timings[name] = round(time.perf_counter() - t0, 2)

    _say(args, f"HOPE Seed Trainer demo -> {out}\n")
    t0 = time.perf_counter()
    if (raw / "clean").exists():
        _say(args, "1. episodes: reusing the ones generated earlier (use --fresh to regenerate)")
    else:
        g = generate_dataset(raw / "clean", args.steps, seed=args.seed, imagined_fraction=0.1,
                             episode_seconds=(20.0, 40.0), id_prefix="demo")
        _say(args, f"1. generated {g.episodes} episodes ({g.imagined_episodes} imagined), {g.steps} steps "
                   f"at 10/20/50 Hz in {g.seconds:.1f} s")
        expected = make_messy_sources(raw, raw / "clean")
        _say(args, "   plus the shapes real producers write:")
        for name, outcome in expected.items():
            _say(args, f"     messy/{name:<22} expected: {outcome}")
    timed("generate", t0)

    t0 = time.perf_counter()
    report = validate_paths([raw], profile="train")
    timed("validate", t0)
    s = report["summary"]
    _say(args, f"\n2. validate --profile train: {s['episodes']} episodes, {s['steps']} steps: "
               f"{s['accepted']} accepted, {s['accepted_with_warnings']} with warnings, "
               f"{s['partly_recovered']} partly recovered, {s['rejected']} rejected, {s['skipped']} skipped")
    for e in report["episodes"]:
        if "/messy/" in e["source"] or e["status"] == "rejected":
            first = (e["errors"] or e["warnings"] or ["no findings"])[0]
            _say(args, f"     {e['status']:<22} {Path(e['source']).name}: {first.split(': ', 1)[-1][:100]}")

    t0 = time.perf_counter()
    first = ingest_paths([raw], dataset)["summary"]
    second = ingest_paths([raw], dataset)["summary"]
    timed("ingest", t0)
    _say(args, f"\n3. ingest -> {dataset}: {first['written']} written, {first['unchanged']} unchanged, "
               f"{first['rejected']} rejected, {first['skipped']} skipped")
    _say(args, f"   ingest again: {second['written']} written, {second['unchanged']} unchanged "
               "(idempotent: same ids, nothing rewritten)")
    recheck = validate_paths([dataset], profile="train")["summary"]
    _say(args, f"   validate the dataset: {'ok' if recheck['ok'] else 'NOT OK'} ({recheck['episodes']} episodes)")

    t0 = time.perf_counter()
    summary = summarise_dataset(dataset, cache_root)
    timed("cache", t0)
    _say(args, "\n4. dataset, feature spec and cache:\n   " + format_summary(summary).replace("\n", "\n   "))
    reused = summarise_dataset(dataset, cache_root)["reused"]
    _say(args, f"   second open: cache {'reused' if reused else 'REBUILT (unexpected)'}")

    t0 = time.perf_counter()
    cache, _ = load_or_build(dataset, cache_root)
    sampler = AnchorSampler(cache, batch_size=64, seed=args.seed, imagined_ratio=0.1, min_history_s=0.1)
    fast, mid = window_spec("fast"), window_spec("mid", horizons_s=(1.0,))
    n_batches = 200
    for _ in range(n_batches):
        batch = make_windows(cache, sampler.next_batch(), fast)
    fast_rate = n_batches / (time.perf_counter() - t0)
    state = sampler.state_dict()
    resumed = AnchorSampler(cache, batch_size=64, seed=args.seed, imagined_ratio=0.1, min_history_s=0.1)
    resumed.load_state_dict(state)
    same = bool(np.array_equal(resumed.next_batch(), sampler.next_batch()))
    mid_batch = make_windows(cache, sampler.next_batch(), mid)
    timed("windows", t0)
    _say(args, "\n5. windows (cut by time, resampled to a fixed grid):")
    _say(args, f"   fast {fast.duration_s * 1000:.0f} ms x {fast.k} points: obs {list(batch.obs.shape)}, "
               f"act {list(batch.act.shape)}, {fast_rate:.0f} batches/s of 64")
    _say(args, f"   mid {mid.duration_s:.0f} s x {mid.k} points + 1 s ahead: obs {list(mid_batch.obs.shape)}, "
               f"future {list(mid_batch.future_obs.shape)}, {int(mid_batch.mask.sum())} of "
               f"{mid_batch.mask.size} grid points inside their episodes")
    _say(args, f"   sampler resumed from its saved position draws the same next batch: {same}")

    training: list[dict[str, Any]] = []
    if args.train_steps > 0:
        t0 = time.perf_counter()
        _say(args, f"\n6. training vqvae, fast_loop, mid_loop for {args.train_steps} steps each, "
                   "each in its own process (progress below):")
        training = _train_sequence(args, dataset, cache_root, out / "runs")
        timed("train", t0)
        if not args.json:
            from hope_models.train.sequential import format_table
            print("   " + format_table(training).replace("\n", "\n   "))

    result: dict[str, Any] = {
        "out": str(out),
        "validate": s,
        "ingest_first": first,
        "ingest_second": second,
        "dataset_ok": recheck["ok"],
        "dataset": {k: summary[k] for k in ("episodes", "steps", "imagined_episodes", "rates", "obs_dim",
                                             "act_dim", "cache_path", "fingerprint")},
        "cache_reused_on_second_open": reused,
        "fast_batches_per_s": round(fast_rate, 1),
        "training": training,
        "sampler_resume_identical": same,
        "seconds": timings,
        "total_seconds": round(time.perf_counter() - started, 1),
    }
    trained_ok = all(r.get("outcome") == "completed" for r in training) and (
        args.train_steps == 0 or len(training) == 3)
    ok = (recheck["ok"] and second["written"] == 0 and reused and same and s["rejected"] >= 1 and trained_ok)
    result["ok"] = ok
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        for r in training:
            if r.get("outcome") != "completed":
                print(f"training {r['component']} did not complete: {r.get('message', r.get('outcome'))}")
        print(f"\nSummary: {summary['episodes']} episodes / {summary['steps']} steps ingested and cached; "
              f"{s['rejected']} rejected with reasons; re-ingest changed nothing; "
              f"total {result['total_seconds']:.1f} s. {'OK' if ok else 'SOMETHING IS WRONG (see above)'}")
    return 0 if ok else 1
