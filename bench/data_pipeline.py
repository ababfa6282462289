#!/usr/bin/env python3
"""Data pipeline benchmark: memory-mapped cache + time windows vs. JSON dicts in RAM.

Prints figures; it is not a test. One run:
  1. generates a canonical dataset of --steps steps (20-dim obs, 6-dim actions, 10/20/50 Hz) and
     one 4x larger,
  2. builds the cache of each (own subprocess: build steps/s and build peak RSS),
  3. samples fast windows (batch 64) from each cache in a fresh subprocess that only opens the
     cache and samples (batches/s, peak RSS while sampling), with the sampler's default (every
     anchor on its own) and with 4 anchors a block (opt-in, sampler.py: one read a block),
  4. runs the BASELINE in its own subprocess: every JSONL line loaded into Python dicts, a list of
     dict steps per episode, windows built per batch from those lists (same time grid and
     zero-order hold via bisect, so the outputs are identical; checked on a few hundred anchors),
  5. prints a table and PASS/FAIL for: batches/s >= 20x baseline; sampling RSS <= 1/5 of the
     baseline's; sampling RSS growth < 50 MB when the dataset grows 4x; the 4x cache read inside
     the resident budget at >= 10k batches/s, its pages resident in this process within the budget.

With --before DIR (a checkout of an earlier version, e.g. `git worktree add DIR <commit>`), step 3
also runs DIR's own sampling child on the same caches, interleaved with ours, so the two are
compared under the same load; --rounds N repeats the sampling children and reports medians.

    python bench/data_pipeline.py [--steps 500000] [--out DIR] [--keep] [--before DIR] [--rounds N]
"""
from __future__ import annotations

import argparse
import bisect
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

BATCH = 64
from hope_models.data.cache import DEFAULT_RESIDENT_BUDGET_MB  # noqa: E402 (after the sys.path setup)

MB = 1 << 20


def _rss() -> tuple[int, int]:
    import psutil

    m = psutil.Process().memory_info()
    return m.rss, m.rss - m.shared  # total, anonymous (not file-backed)


# -- subprocess bodies ---------------------------------------------------------------------------

def child_build(dataset: str, cache_root: str) -> dict:
    import resource

    from hope_models.data.cache import load_or_build

    t0 = time.perf_counter()
    cache, info = load_or_build(dataset, cache_root)
    total = time.perf_counter() - t0
    return {"steps": cache.n_steps, "episodes": cache.n_episodes, "path": str(info.path), "reused": info.reused,
            "build_s": info.build_seconds, "fingerprint_s": info.fingerprint_seconds, "total_s": total,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "excluded": len(cache.manifest["excluded"])}


def child_sample(cache_path: str, batches: int, budget_mb: float, anchors_per_block: int = 1) -> dict:
    from hope_models.data.cache import open_cache
    from hope_models.data.sampler import AnchorSampler
    from hope_models.data.windows import WindowLoader, window_spec

    rss0 = _rss()
    cache = open_cache(cache_path, resident_budget_mb=budget_mb)
    sampler = AnchorSampler(cache, BATCH, seed=0, split="all", anchors_per_block=anchors_per_block)
    loader = WindowLoader(cache, sampler, window_spec("fast"))
    next(loader)  # first use computes the block length from t (once per window length)
    peak, peak_anon = _rss()
    t0 = time.perf_counter()
    for b in range(batches):
        next(loader)
        if b % 16 == 0:
            r, a = _rss()
            peak, peak_anon = max(peak, r), max(peak_anon, a)
    dt = time.perf_counter() - t0
    r, a = _rss()
    return {"batches_per_s": batches / dt, "batches": batches, "rss_start_mb": rss0[0] / MB, "mode": cache.mode,
            "peak_rss_mb": max(peak, r) / MB, "peak_anon_mb": max(peak_anon, a) / MB,
            "cache_pages_mb": _cache_pages(cache_path) / MB,
            "anchors_per_block": sampler.anchor_group[0]}


def _cache_pages(cache_path: str) -> int:
    """Bytes of this process's resident pages mapped from the cache's files (/proc/self/smaps; a
    mapping's resident pages only grow while nothing reclaims them, so the end is the peak)."""
    smaps = Path("/proc/self/smaps")
    if not smaps.exists():
        return 0
    total, inside = 0, False
    for line in smaps.read_text().splitlines():
        head = line.split()
        if head and "-" in head[0] and ":" not in head[0]:
            inside = len(head) >= 6 and head[5].startswith(cache_path)
        elif inside and line.startswith("Rss:"):
            total += int(head[1]) * 1024
    return total


def _baseline_load(dataset: str) -> tuple[list[list[dict]], list[list[float]]]:
    """How the reference implementation held data: every step a dict, per episode a list."""
    episodes, times = [], []
    for ep_dir in sorted(p for p in Path(dataset).iterdir() if p.is_dir()):
        steps: list[dict] = []
        for f in sorted((ep_dir / "steps").glob("*.jsonl")):
            with open(f, encoding="utf-8") as fh:
                steps.extend(json.loads(line) for line in fh if line.strip())
        t0 = steps[0]["timestamp_ns"]
        episodes.append(steps)
        times.append([(s["timestamp_ns"] - t0) / 1e9 for s in steps])
    return episodes, times


def _baseline_windows(episodes, times, offsets, anchors, lags, spec_paths, norm, eps=1e-6):
    """Windows from lists: bisect the episode's time list per grid point, walk each step dict along
    the spec's field paths (the pipeline is generic over datasets, so is the baseline), then
    convert the batch to arrays."""
    obs_paths, act_paths = spec_paths
    obs_rows, act_rows, mask_rows = [], [], []
    for g in anchors:
        e = bisect.bisect_right(offsets, g) - 1
        i = g - offsets[e]
        steps, ts = episodes[e], times[e]
        ta = ts[i]
        for lag in lags:
            k = min(bisect.bisect_right(ts, ta - lag + eps) - 1, i)
            mask_rows.append(k >= 0)
            s = steps[max(k, 0)]
            for paths, rows in ((obs_paths, obs_rows), (act_paths, act_rows)):
                row = []
                for path in paths:
                    v = s
                    for part in path:
                        v = v[part]
                    row.extend(v) if isinstance(v, list) else row.append(v)
                rows.append(row)
    b, k = len(anchors), len(lags)
    obs = np.asarray(obs_rows, dtype=np.float32).reshape(b, k, -1)
    act = np.asarray(act_rows, dtype=np.float32).reshape(b, k, -1)
    mask = np.asarray(mask_rows, dtype=bool).reshape(b, k)
    obs = (obs - norm[0]) / norm[1]
    act = (act - norm[2]) / norm[3]
    obs[~mask] = 0.0
    act[~mask] = 0.0
    return obs, act, mask


def child_baseline(dataset: str, batches: int, spec_path: str, dump: str | None) -> dict:
    import random

    from hope_models.data.spec_request import load_spec
    from hope_models.data.windows import window_spec

    spec = load_spec(spec_path)
    norm = spec.normalizer()
    paths = tuple([tuple(f.path.split(".")) for f in g.fields] for g in (spec.observation, spec.action))
    rss0 = _rss()
    t0 = time.perf_counter()
    episodes, times = _baseline_load(dataset)
    load_s = time.perf_counter() - t0
    offsets = [0]
    for ep in episodes:
        offsets.append(offsets[-1] + len(ep))
    n = offsets[-1]
    lags = window_spec("fast").lags.tolist()
    rng = random.Random(0)
    peak, peak_anon = _rss()
    t0 = time.perf_counter()
    for b in range(batches):
        anchors = [rng.randrange(n) for _ in range(BATCH)]
        _baseline_windows(episodes, times, offsets, anchors, lags, paths, norm)
        if b % 16 == 0:
            r, a = _rss()
            peak, peak_anon = max(peak, r), max(peak_anon, a)
    dt = time.perf_counter() - t0
    out = {"batches_per_s": batches / dt, "batches": batches, "load_s": load_s, "steps": n,
           "rss_start_mb": rss0[0] / MB, "peak_rss_mb": peak / MB, "peak_anon_mb": peak_anon / MB}
    if dump:
        checked = np.random.default_rng(1).integers(0, n, 512)
        obs, act, mask = _baseline_windows(episodes, times, offsets, checked.tolist(), lags, paths, norm)
        np.savez(dump, anchors=checked, obs=obs, act=act, mask=mask)
    return out


def _run_child(*args: str, tree: Path = REPO) -> dict:
    """A child of this bench, or with `tree` the same child of another checkout's bench (its own
    library on the path, so its data layer is the one timed)."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    proc = subprocess.run([sys.executable, str(tree / "bench" / "data_pipeline.py"), "_child", *args],
                          capture_output=True, text=True, cwd=tree, env=env)
    if proc.returncode != 0:
        raise SystemExit(f"child {args[0]} ({tree}) failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _sample_rounds(path: str, a, trees: dict[str, Path]) -> dict[str, dict]:
    """Each tree's sampling child all mapped, then inside the budget (ours also with 4 anchors a
    block), interleaved for --rounds rounds; per tree and kind the run with the median batches/s
    (its RSS figures with it). The mapped children go first and an untimed budget child follows
    them: a child that starts right after one that mapped the whole file measured 0.8-1.05x the
    next one, and in a fixed order that slot fell on the same tree every round."""
    runs: dict[str, list[dict]] = {}

    def child(key: str, tree: Path, budget: str, *more: str) -> None:
        runs.setdefault(key, []).append(_run_child("sample", path, str(a.batches), budget, *more, tree=tree))

    for _ in range(a.rounds):
        for name, tree in trees.items():
            child(f"{name}:mapped", tree, "1e9")
    _run_child("sample", path, str(a.batches), str(a.budget_mb), tree=REPO)  # settles, not timed
    kinds = [(f"{name}:sample", tree, ()) for name, tree in trees.items()] + [("ours:grouped", REPO, ("4",))]
    for r in range(a.rounds):
        for key, tree, more in kinds[r % len(kinds):] + kinds[:r % len(kinds)]:  # each kind first in turn
            child(key, tree, str(a.budget_mb), *more)
    return {key: sorted(rs, key=lambda r: r["batches_per_s"])[len(rs) // 2] for key, rs in runs.items()}


# -- the run -------------------------------------------------------------------------------------

def _check_equal(cache_path: str, dump: str) -> float:
    from hope_models.data.cache import open_cache
    from hope_models.data.windows import make_windows, window_spec

    ref = np.load(dump, allow_pickle=False)
    w = make_windows(open_cache(cache_path), ref["anchors"], window_spec("fast"))
    if not np.array_equal(w.mask, ref["mask"]):
        raise SystemExit("ours and the baseline disagree on the window mask")
    return float(max(np.abs(w.obs - ref["obs"]).max(), np.abs(w.act - ref["act"]).max()))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=500_000, help="steps of the base dataset (the large one is 4x)")
    p.add_argument("--out", help="work dir for datasets and caches (default: a temp dir)")
    p.add_argument("--keep", action="store_true", help="keep the generated datasets and caches")
    p.add_argument("--batches", type=int, default=4000, help="batches timed for our sampler")
    p.add_argument("--baseline-batches", type=int, default=400)
    p.add_argument("--budget-mb", type=float, default=DEFAULT_RESIDENT_BUDGET_MB,
                   help="resident budget of the cache reader (default: the library default)")
    p.add_argument("--before", type=Path, help="a checkout of an earlier version, timed beside ours on the same caches")
    p.add_argument("--rounds", type=int, default=1, help="sampling runs per tree and cache, medians reported")
    a = p.parse_args(argv)
    if a.before is not None and not (a.before / "bench" / "data_pipeline.py").is_file():
        raise SystemExit(f"--before {a.before}: no bench/data_pipeline.py there; give a checkout of this repository")
    trees = {"ours": REPO} | ({"before": a.before.resolve()} if a.before is not None else {})

    from hope_models.data.synthetic import generate_dataset

    work = Path(a.out) if a.out else Path(tempfile.mkdtemp(prefix="hope-bench-"))
    work.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    rows: dict[str, dict] = {}
    try:
        sizes = {"1x": a.steps, "4x": 4 * a.steps}
        for tag, n in sizes.items():
            ds = work / f"dataset_{tag}"
            if ds.exists():
                shutil.rmtree(ds)
            g = generate_dataset(ds, n, obs_dim=20, act_dim=6, rates_hz=(10, 20, 50), seed=0)
            print(f"generated {tag}: {g.episodes} episodes, {g.steps} steps, {g.bytes_written / 1e6:.0f} MB "
                  f"in {g.seconds:.1f} s", flush=True)
            cache_root = work / f"cache_{tag}"
            shutil.rmtree(cache_root, ignore_errors=True)
            build = _run_child("build", str(ds), str(cache_root))
            print(f"built {tag}: {build['steps']} steps in {build['build_s']:.1f} s "
                  f"(+{build['fingerprint_s']:.1f} s fingerprint), peak RSS {build['peak_rss_mb']:.0f} MB", flush=True)
            timed = _sample_rounds(build["path"], a, trees)  # "mapped": all mapped, for reference
            rows[tag] = {"dataset": str(ds), "gen": g.seconds, "build": build, "sample": timed["ours:sample"],
                         "grouped": timed["ours:grouped"],
                         "mapped": timed["ours:mapped"], "before": timed.get("before:sample"),
                         "before_mapped": timed.get("before:mapped")}
        dump = str(work / "baseline_windows.npz")
        spec = str(Path(rows["1x"]["build"]["path"]) / "spec.json")
        base = _run_child("baseline", rows["1x"]["dataset"], str(a.baseline_batches), spec, dump)
        max_diff = _check_equal(rows["1x"]["build"]["path"], dump)
        total = time.perf_counter() - started
        _report(a, rows, base, max_diff, total)
    finally:
        if not a.keep:
            shutil.rmtree(work, ignore_errors=True)
        else:
            print(f"kept {work}")
    return 0


def _report(a, rows: dict, base: dict, max_diff: float, total: float) -> None:
    one, four = rows["1x"], rows["4x"]
    print()
    print(f"{'':34s} {'ours 1x':>12s} {'ours 4x':>12s} {'baseline 1x':>12s}")
    line = lambda label, x, y, z: print(f"{label:34s} {x:>12s} {y:>12s} {z:>12s}")  # noqa: E731
    line("steps", f"{one['build']['steps']:,}", f"{four['build']['steps']:,}", f"{base['steps']:,}")
    line("cache build steps/s", f"{one['build']['steps'] / one['build']['build_s']:,.0f}",
         f"{four['build']['steps'] / four['build']['build_s']:,.0f}", "-")
    line("build peak RSS MB", f"{one['build']['peak_rss_mb']:.0f}", f"{four['build']['peak_rss_mb']:.0f}", "-")
    line("load into dicts s", "-", "-", f"{base['load_s']:.1f}")
    line("access mode (resident budget)", f"{one['sample']['mode']}", f"{four['sample']['mode']}", "dicts")
    line("fast-window batches/s (B=64)", f"{one['sample']['batches_per_s']:,.0f}",
         f"{four['sample']['batches_per_s']:,.0f}", f"{base['batches_per_s']:,.0f}")
    line("peak RSS while sampling MB", f"{one['sample']['peak_rss_mb']:.0f}", f"{four['sample']['peak_rss_mb']:.0f}",
         f"{base['peak_rss_mb']:.0f}")
    line("  of which anonymous MB", f"{one['sample']['peak_anon_mb']:.0f}", f"{four['sample']['peak_anon_mb']:.0f}",
         f"{base['peak_anon_mb']:.0f}")
    line("all mapped (no budget): batches/s", f"{one['mapped']['batches_per_s']:,.0f}",
         f"{four['mapped']['batches_per_s']:,.0f}", "-")
    line("all mapped (no budget): RSS MB", f"{one['mapped']['peak_rss_mb']:.0f}",
         f"{four['mapped']['peak_rss_mb']:.0f}", "-")
    line("cache pages resident MB", f"{one['sample']['cache_pages_mb']:.1f}",
         f"{four['sample']['cache_pages_mb']:.1f}", "-")
    for label, key, f in (("4 anchors a block (opt-in): batches/s", "batches_per_s", ",.0f"),
                          ("4 anchors a block: peak RSS MB", "peak_rss_mb", ".0f"),
                          ("4 anchors a block: cache pages MB", "cache_pages_mb", ".1f")):
        line(label, format(one["grouped"][key], f), format(four["grouped"][key], f), "-")
    if four["before"] is not None:
        num = lambda r, key, f: "-" if key not in r else format(r[key], f)  # noqa: E731 (older children lack keys)
        for label, kind, key, f in (("before: batches/s (B=64)", "before", "batches_per_s", ",.0f"),
                                    ("before: peak RSS while sampling MB", "before", "peak_rss_mb", ".0f"),
                                    ("before: cache pages resident MB", "before", "cache_pages_mb", ".1f"),
                                    ("before: all mapped batches/s", "before_mapped", "batches_per_s", ",.0f")):
            line(label, num(one[kind], key, f), num(four[kind], key, f), "-")
    print(f"ours vs baseline on 512 anchors: max |diff| = {max_diff:.2e}")
    speed = one["sample"]["batches_per_s"] / base["batches_per_s"]
    mem = one["sample"]["peak_rss_mb"] / base["peak_rss_mb"]
    growth = four["sample"]["peak_rss_mb"] - one["sample"]["peak_rss_mb"]
    verdict = lambda ok: "PASS" if ok else "FAIL"  # noqa: E731
    print()
    print(f"speed: ours / baseline batches/s = {speed:.1f}x (target >= 20x) {verdict(speed >= 20)}")
    print(f"memory: ours / baseline sampling RSS = 1/{1 / mem:.1f} (target <= 1/5) {verdict(mem <= 0.2)}")
    print(f"growth: sampling RSS 4x - 1x = {growth:+.1f} MB (target < 50 MB) {verdict(growth < 50)}")
    budgeted, pages = four["sample"]["batches_per_s"], four["sample"]["cache_pages_mb"]
    print(f"budget: 4x batches/s in {four['sample']['mode']} mode = {budgeted:,.0f} (target >= 10,000) "
          f"{verdict(budgeted >= 10_000)}")
    print(f"budget: 4x cache pages resident = {pages:.1f} MB (budget {a.budget_mb:g} MB) {verdict(pages <= a.budget_mb)}")
    grouped, gpages = four["grouped"]["batches_per_s"], four["grouped"]["cache_pages_mb"]
    print(f"budget, 4 anchors a block (opt-in): 4x batches/s = {grouped:,.0f} (target >= 10,000) "
          f"{verdict(grouped >= 10_000)}, cache pages {gpages:.1f} MB {verdict(gpages <= a.budget_mb)}")
    if four["before"] is not None:
        print(f"before: 4x batches/s in the budget, ours / before = {budgeted / four['before']['batches_per_s']:.2f}x, "
              f"all mapped {four['mapped']['batches_per_s'] / four['before_mapped']['batches_per_s']:.2f}x, "
              f"4 anchors a block {grouped / four['before']['batches_per_s']:.2f}x "
              f"({a.rounds} round(s), medians)")
    print(f"total bench time {total:.0f} s on {os.cpu_count()} cores")


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "_child":
        kind, rest = sys.argv[2], sys.argv[3:]
        if kind == "build":
            result = child_build(*rest)
        elif kind == "sample":
            result = child_sample(rest[0], int(rest[1]), float(rest[2]), *(int(r) for r in rest[3:4]))
        else:
            result = child_baseline(rest[0], int(rest[1]), rest[2], rest[3] if len(rest) > 3 else None)
        print(json.dumps(result))
        sys.exit(0)
    sys.exit(main())
