"""Inference benchmark: the fast_loop's one-tick latency, the hot-swap pause, the loop-closure time.

1. One tick at batch 1, every form in the same run, interleaved in blocks so machine noise falls
   on all of them alike (default model size: d_model 128, d_state 256, K=5, trained briefly):
   - the recurrent NumPy form (FastLoopNumpyAct.act: the tick BrainService runs, normalisation folded in),
   - the whole service call (BrainService.infer with a session: validation, lock, state, answer),
   - torch's recurrent form (FastLoop.step), for reference,
   - re-running the whole window each tick: torch FastLoop.forward on the last K observations,
     and the NumPy FastLoopNumpy.forward on them.
   Targets: p99 < 1 ms, and the recurrent form >= 5x faster than the window re-run.
   --k-scaling adds a K=20 model (same width) to show how both forms grow with the window.
2. The swap pause: a client thread calls BrainService.infer in a tight loop while the pointer is
   rewritten --swaps times (alternating two checkpoints); requests between a pointer write and 50 ms
   after the first answer from the new version are "during a swap", the rest "normal".
   Target (the test's): p99 during swaps <= 3x the normal p99, no failed request.
3. The loop-closure time, in-process: a fresh $HOPE_HOME with the registry; a queued run is
   created as `enqueue` does (registry.run_request.submit), marked running, trained in this process
   through hope_models.train.loop.train (the worker's code path, minus the broker), and finished
   with registry.runs.finish (finished_at). Then the gate, two ways, alternating (--closures runs
   each): "warm", in this process right after training, what the worker child that trained the run
   does before it exits (workers/warm_gate.py); "child", `run_trainer.py promote RUN --auto --json`
   as a child process, what the daemon's auto-promotion spawns when no worker gated the run (torch
   imported first). Either gate measures the validation loss of the candidate, and of the promoted
   model on the same split from the second run on. BrainService (poll 0.2 s) follows the pointer, and a "robot" thread asks for an action
   every 20 ms (a 50 Hz control loop); on_first_inference records first_inference_at and
   loop_closure_s through registry.promotion.record_first_inference, as the webapp does. The figure
   is the registry's loop_closure_s. With the daemon, a child gate starts up to one daemon tick
   (0.5 s) later.
4. The RSS of a fresh process holding BrainService with the model loaded (no torch imported).
5. The full answer: BrainService with all three components promoted (default sizes: the fast_loop
   above, a VQ-VAE of 3 groups x 128 codes, a Mid Loop d_model 128 x 2 blocks reading it, K=20,
   horizons 0.5 s / 1 s), one session ticked back to back as a 50 Hz robot's ticks (a Mid Loop grid
   point every 5th tick), interleaved in blocks with a fast_loop-only service on the same
   observations: p50/p99 of every tick, of the grid-point ticks alone and of the others. Also the
   Mid Loop's ways to a prediction from the last K points: the window form (MidLoopNumpy.forward),
   re-stepping K points from a fresh state, and what BrainService runs: the window but its last
   point ahead (window_ahead + ahead_step, spread over the ticks between grid points), then the
   last point alone (predict with ahead).
   Target: p99 of the full answer <= 1 ms. The thread CPU time of each tick is recorded too: on a
   shared machine the wall-clock p99 of a 0.2-0.7 ms call is set by preemption (a call hit by the
   scheduler waits a time slice, ~4 ms), which the CPU time does not count.
6. The full answer from a camera frame: BrainService serving a grid VQ-VAE as the tokenizer (the
   layout docs/training.md chose: 64x64, patch 4 = 16x16 cells, 256 codes, channels 16) and a
   default-size fast_loop over it (d_model 128, d_state 256, 16 keypoints), random weights (the
   cost is the arithmetic's, not the training's), one session ticked with the joints and the
   frame: the answer (decode the frame, encode it once for both, the reflex's tick, the codes) with
   the frame sent raw, as a base64 PNG and as a base64 JPEG; the same with a tokenizer whose VQ-VAE
   differs from the reflex's (two encodes); the whole brain from the frame: a default-size grid
   Mid Loop (mid_loop/numpy_grid.py: d_model 128, K=20, horizons 0.5 s / 1 s, cell rank 32) over
   the same VQ-VAE added (one encode for all three; at its grid points, every 5th tick, the
   window's last point, the joints ahead and the surprise of each horizon's 256 cells), every
   tick and its grid-point ticks alone; the frame encode alone and the reflex's tick alone.
   Targets: p99 of the frame answer (raw frame) and of the whole brain's <= 3 ms on one core.

    .venv/bin/python bench/inference.py                 # --ticks 4000 --swaps 6 --closures 2
    .venv/bin/python bench/inference.py --k-scaling --json
    .venv/bin/python bench/inference.py --frame-only    # section 6 alone (~1 min)

It prints figures; it is not a test.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from datetime import datetime
from itertools import pairwise
from pathlib import Path
from typing import Any, Callable

# One BLAS thread, set before numpy loads OpenBLAS: torch runs with one thread here too, and on 2
# shared cores a second BLAS thread only adds scheduling tails to the batched (window) products.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))  # frame_fixtures: the moving scene the frame tests use too

from frame_fixtures import moving_frames  # noqa: E402

TARGET_P99_MS = 1.0
TARGET_WHOLE_P99_MS = 1.0
TARGET_SPEEDUP = 5.0
TARGET_SWAP_RATIO = 3.0
TARGET_FRAME_P99_MS = 3.0
WHOLE_FRAME = "frame answer + grid Mid Loop (encode + fast + mid + surprise)"
FRAME_VQ = {"input": "frame", "layout": "grid", "patch": 4, "n_codes": 256, "channels": 16}  # docs/training.md's grid
CONTROL_PERIOD_S = 0.02


# -- fixtures --------------------------------------------------------------------------------------

def make_dataset(root: Path) -> Path:
    from hope_models.data.synthetic import generate_dataset

    ds = root / "ds"
    if not ds.exists():  # the reacher's sizes: 6 observation values, 2 action values
        generate_dataset(ds, 3000, obs_dim=6, act_dim=2, episode_seconds=(10, 30), seed=0)
    return ds


def train_run(data: Path, run_dir: Path, cache: Path, steps: int, every: int, model_config: dict | None = None,
              component: str = "fast_loop", vqvae_dir: Path | None = None) -> Path:
    from hope_models.train.loop import TrainConfig, train

    res = train(TrainConfig(component=component, vqvae_dir=None if vqvae_dir is None else str(vqvae_dir), data=str(data), run_dir=str(run_dir), steps=steps, seed=0,
                            batch_size=32, threads=1, checkpoint_every_steps=every, log_every=50,
                            cache_dir=str(cache), thermal_zone=None, vcgencmd=None,
                            model_config=model_config or {}, val_batches=2))
    if res.outcome != "completed":
        raise SystemExit(f"training {run_dir} did not complete: {res.outcome}: {res.message}")
    return Path(res.checkpoint)


def write_pointer(home: Path, ckpt: Path, model_id: int = 1, component: str = "fast_loop") -> None:
    from datetime import datetime, timezone

    from hope_models.promoted import checkpoint_version
    from hope_models.promoted import write_pointer as write

    version, sha = checkpoint_version(ckpt)
    write(home, component, {"component": component, "checkpoint": str(ckpt.resolve()), "version": version,
                              "sha256": sha, "model_id": model_id, "run_id": None,
                              "promoted_at": datetime.now(timezone.utc).isoformat()})


def pct(values, q: float) -> float:
    return float(np.percentile(np.asarray(values), q))


def summary_ms(lat_s: list[float]) -> dict[str, float]:
    ms = np.asarray(lat_s) * 1e3
    return {"p50_ms": round(pct(ms, 50), 4), "p99_ms": round(pct(ms, 99), 4), "mean_ms": round(float(ms.mean()), 4),
            "max_ms": round(float(ms.max()), 3), "n": int(ms.size)}


# -- 1. one tick ---------------------------------------------------------------------------------------

def tick_latency(ckpt: Path, home: Path, ticks: int, block: int = 250) -> dict[str, Any]:
    import torch

    from hope_models.components.build import component_from_checkpoint
    from hope_models.components.fast_loop.numpy_act import FastLoopNumpyAct
    from hope_models.runtime.brain_service import BrainService

    torch.set_num_threads(1)
    model = FastLoopNumpyAct.from_checkpoint(ckpt)
    tmodel = component_from_checkpoint(ckpt).model.eval()
    k = model.window_k
    rng = np.random.default_rng(0)
    raw = rng.normal(0, 1, (ticks + k, model.obs_dim))
    raw_lists = raw.tolist()
    write_pointer(home, ckpt)
    brain = BrainService(home)
    brain.check_now()

    # Each form keeps its own rolling context, so every call is a real tick of a running episode.
    np_state = [model.init_state()]
    t_state = [tmodel.init_state(1)]
    window = np.zeros((k, model.obs_dim), np.float32)  # the last K normalised observations, oldest first

    def numpy_recurrent(i):
        _, np_state[0] = model.act(raw[i], np_state[0])

    def service(i):
        brain.infer("fast_loop", raw_lists[i], session="bench")

    def torch_recurrent(i):
        xn = torch.from_numpy(model.normalise(raw[i])[None, :])
        with torch.inference_mode():
            a, t_state[0] = tmodel.step(xn, t_state[0])
        model.denormalise(a[0].numpy())

    def push(i):
        window[:-1] = window[1:]
        window[-1] = model.normalise(raw[i])

    def torch_window(i):
        push(i)
        with torch.inference_mode():
            a = tmodel(torch.from_numpy(window[None]))
        model.denormalise(a[0].numpy())

    def numpy_window(i):
        push(i)
        model.denormalise(model.forward(window[None])[0])

    forms: dict[str, Callable[[int], None]] = {
        "numpy recurrent (FastLoopNumpyAct.act)": numpy_recurrent,
        "BrainService.infer (session)": service,
        "torch recurrent (FastLoop.step)": torch_recurrent,
        "torch window re-run (FastLoop.forward)": torch_window,
        "numpy window re-run (FastLoopNumpy.forward)": numpy_window,
    }
    lat: dict[str, list[float]] = {name: [] for name in forms}
    for fn in forms.values():  # warm-up
        for i in range(50):
            fn(i)
    perf = time.perf_counter
    for start in range(0, ticks, block):
        for name, fn in forms.items():
            out = lat[name]
            for i in range(start, min(start + block, ticks)):
                t0 = perf()
                fn(i)
                out.append(perf() - t0)
    res = {name: summary_ms(v) for name, v in lat.items()}
    return {"model": repr(model), "k": k, "d_model": model.d_model, "d_state": model.d_state, "forms": res}


# -- 2. the swap pause ---------------------------------------------------------------------------------

def swap_pause(ckpt_a: Path, ckpt_b: Path, home: Path, swaps: int) -> dict[str, Any]:
    from hope_models.promoted import checkpoint_version
    from hope_models.runtime.brain_service import BrainService

    va, vb = checkpoint_version(ckpt_a)[0], checkpoint_version(ckpt_b)[0]
    write_pointer(home, ckpt_a)
    results: list[tuple[float, float, str]] = []
    failures: list[str] = []
    stop = threading.Event()
    brain = BrainService(home).start()
    rng = np.random.default_rng(1)
    obs = rng.normal(0, 1, (1024, 6)).tolist()

    def client():
        i = 0
        perf = time.perf_counter
        while not stop.is_set():
            t0 = perf()
            try:
                out = brain.infer("fast_loop", obs[i & 1023], session="robot")
            except Exception as exc:  # noqa: BLE001 - every failure counts
                failures.append(repr(exc))
                continue
            finally:
                i += 1
            results.append((t0, perf() - t0, out["model_version"]))

    thread = threading.Thread(target=client, daemon=True)
    thread.start()
    writes: list[tuple[float, str]] = []
    load_ms = []
    try:
        time.sleep(1.0)
        for n in range(swaps):
            ckpt, want = (ckpt_b, vb) if n % 2 == 0 else (ckpt_a, va)
            t_write = time.perf_counter()
            write_pointer(home, ckpt, model_id=n + 2)
            writes.append((t_write, want))
            deadline = time.monotonic() + 5
            while brain.version("fast_loop") != want and time.monotonic() < deadline:
                time.sleep(0.002)
            load_ms.append((time.perf_counter() - t_write) * 1e3)
            time.sleep(0.8)
    finally:
        stop.set()
        thread.join(10)
        brain.stop()
    windows = []
    for t_write, want in writes:
        first_new = next((t for t, _, v in results if t >= t_write and v == want), None)
        windows.append((t_write, (first_new if first_new is not None else t_write + 1.0) + 0.05))
    during, normal = [], []
    for t, lat, _ in results:
        (during if any(a <= t <= b for a, b in windows) else normal).append(lat)
    versions = [v for _, _, v in results]
    switches = sum(1 for a, b in pairwise(versions) if a != b)
    out = {"requests": len(results), "failures": len(failures), "swaps": swaps, "version_switches": switches,
           "normal": summary_ms(normal), "during_swaps": summary_ms(during),
           "pointer_to_swap_ms": {"median": round(statistics.median(load_ms), 1), "max": round(max(load_ms), 1)}}
    out["p99_ratio"] = round(out["during_swaps"]["p99_ms"] / out["normal"]["p99_ms"], 2)
    return out


# -- 3. the loop-closure time ---------------------------------------------------------------------------

def _gate_in_child(run_id: str, env: dict[str, str]) -> dict[str, Any]:
    """What the daemon's auto-promotion spawns when no worker gated the run: a fresh `promote` child."""
    proc = subprocess.run([sys.executable, str(REPO / "run_trainer.py"), "promote", run_id, "--auto", "--json"],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=900)
    try:
        return json.loads(proc.stdout.strip().splitlines()[-1])
    except (ValueError, IndexError) as exc:
        raise SystemExit(f"promote {run_id}: no JSON answer (exit {proc.returncode}): {proc.stderr[-2000:]}") from exc


def _gate_warm(run_id: str, settings: Any, registry: Any) -> dict[str, Any]:
    """What the worker child that trained the run does before it exits (workers/warm_gate.py): the
    same procedure in the process that has torch loaded and the data's pages in memory."""
    from registry.gating import PromoteRequest, promote_candidate, promote_lock

    with promote_lock(Path(settings.home)):
        return promote_candidate(settings, registry, PromoteRequest(run=run_id, auto=True))[1]


def loop_closure(root: Path, data: Path, closures: int, steps: int,
                 gates: tuple[str, ...] = ("warm", "child")) -> dict[str, Any]:
    from hope_models.runtime.brain_service import BrainError, BrainService
    from hope_models.settings import load_settings
    from hope_models.train.loop import TrainConfig, train
    from registry import promotion, runs
    from registry.db import Registry
    from registry.models import Run
    from registry.run_request import build_request, submit

    home = root / "home"
    env = {k: v for k, v in os.environ.items() if not k.startswith("HOPE_")}
    env.update(HOPE_HOME=str(home), OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    settings = load_settings(home, env=env)
    registry = Registry.open(settings)

    def record(component, version, checkpoint, when):
        with registry.session() as s:
            promotion.record_first_inference(s, checkpoint, when)

    brain = BrainService(home, on_first_inference=record).start()
    seen: dict[str, float] = {}  # version -> wall time of the robot's first answer from it
    stop = threading.Event()

    def robot():
        obs = [0.1, -0.2, 0.3, 0.05, -0.4, 0.2]
        while not stop.is_set():
            try:
                v = brain.infer("fast_loop", obs, session="robot")["model_version"]
                seen.setdefault(v, time.time())
            except BrainError:  # 503 until the first promotion
                pass
            stop.wait(CONTROL_PERIOD_S)

    thread = threading.Thread(target=robot, daemon=True)
    thread.start()
    out = []
    try:
        for n, gate in enumerate(g for _ in range(closures) for g in gates):
            # each run trains longer than the last, so the gate (no worse than the promoted model's
            # validation loss + 5%) has a real reason to pass it
            run_steps = steps * (n + 1)
            req = build_request(component="fast_loop", data=str(data), steps=run_steps)
            with registry.session() as s:
                run = submit(s, settings, req)
                runs.transition(s, run, "starting")  # trained right here, as if a worker child claimed it
                runs.transition(s, run, "running")
                run.worker_pid, run.worker_host = os.getpid(), "bench"
                run_id, run_dir = run.id, run.run_dir
            res = train(TrainConfig(component="fast_loop", data=str(data), run_dir=run_dir, steps=run_steps, seed=0,
                                    threads=1, batch_size=32, log_every=50, checkpoint_every_steps=10 ** 6,
                                    cache_dir=str(settings.cache_dir), thermal_zone=None, vcgencmd=None))
            with registry.session() as s:
                runs.finish(s, run_id, os.getpid(), res.outcome, res.message or "", step=res.steps,
                            last_checkpoint=res.checkpoint)
            t_finished = time.time()
            verdict = _gate_warm(run_id, settings, registry) if gate == "warm" else _gate_in_child(run_id, env)
            t_promoted = time.time()
            if not verdict.get("promoted"):
                out.append({"run": run_id, "gate": gate, "version": verdict.get("version"),
                            "refused": verdict.get("reasons"), "loop_closure_s": None})
                continue
            version = verdict["version"]
            deadline = time.monotonic() + 10
            while version not in seen and time.monotonic() < deadline:
                time.sleep(0.005)
            swapped = brain.status()["fast_loop"]["loaded_at"]
            deadline = time.monotonic() + 5
            closure = None
            while closure is None and time.monotonic() < deadline:
                with registry.session(readonly=True) as s:
                    closure = s.get(Run, run_id).loop_closure_s
                time.sleep(0.02)
            t_loaded = datetime.fromisoformat(swapped).timestamp() if swapped else float("nan")
            out.append({"run": run_id, "gate": gate, "version": version, "train_s": round(res.elapsed_s, 1),
                        "compared_with_promoted": n > 0,
                        "loop_closure_s": closure,
                        "promote_process_s": round(t_promoted - t_finished, 2),
                        "finished_to_loaded_s": round(t_loaded - t_finished, 3),
                        "loaded_to_first_inference_s": round(seen.get(version, float("nan")) - t_loaded, 3),
                        "val_loss": (verdict.get("metrics") or {}).get("candidate_val_loss")})
    finally:
        stop.set()
        thread.join(5)
        brain.stop()
        registry.close()
    return {"closures": out}


# -- 4. memory -------------------------------------------------------------------------------------------

def service_rss(home: Path) -> dict[str, Any]:
    code = f"""
import json, sys, psutil
before = psutil.Process().memory_info().rss
from hope_models.runtime.brain_service import BrainService
brain = BrainService({str(home)!r}).start()
brain.infer("fast_loop", [0.0] * brain.status()["fast_loop"]["obs_dim"], session="s")
after = psutil.Process().memory_info().rss
brain.stop()
print(json.dumps({{"python_mb": before / 2**20, "with_brain_mb": after / 2**20,
                  "torch_imported": "torch" in sys.modules}}))
"""
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    if proc.returncode != 0:
        raise SystemExit(f"RSS probe failed: {proc.stderr[-2000:]}")
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    return {k: (round(v, 1) if isinstance(v, float) else v) for k, v in got.items()}


# -- 5. the full answer -------------------------------------------------------------------------------

def whole_answer(root: Path, data: Path, fast_ckpt: Path, ticks: int, block: int = 250) -> dict[str, Any]:
    from hope_models.components.mid_loop.numpy_form import MidLoopNumpy
    from hope_models.runtime.brain_service import BrainService

    cache = root / "cache"
    vq = train_run(data, root / "runs" / "vq", cache, 20, 20, {}, component="vqvae")
    mid = train_run(data, root / "runs" / "mid", cache, 20, 20, {}, component="mid_loop", vqvae_dir=vq)
    homes = {"whole": root / "home-whole", "fast only": root / "home-fast-only"}
    for name, home in homes.items():
        write_pointer(home, fast_ckpt)
        if name == "whole":
            write_pointer(home, vq, component="vqvae")
            write_pointer(home, mid, component="mid_loop")
    brains = {name: BrainService(home) for name, home in homes.items()}
    for b in brains.values():
        b.check_now()
    raw = np.random.default_rng(0).normal(0, 1, (ticks, 6)).tolist()
    lat: dict[str, list[float]] = {"whole": [], "whole, grid-point ticks": [], "whole, other ticks": [],
                                   "fast only": [], "whole, thread CPU time": [], "fast only, thread CPU time": []}
    done = {name: 0 for name in brains}
    order = list(brains)
    while min(done.values()) < ticks:  # interleaved blocks: machine noise falls on both alike
        for name in order:
            brain, i0 = brains[name], done[name]
            for i in range(i0, min(i0 + block, ticks)):
                c0, t0 = time.thread_time(), time.perf_counter()
                out = brain.infer("fast_loop", raw[i], session="robot")
                dt = time.perf_counter() - t0
                lat[f"{name}, thread CPU time"].append(time.thread_time() - c0)  # what preemption does not add
                lat[name].append(dt)
                if name == "whole":
                    lat["whole, grid-point ticks" if out["mid_tick"] == i else "whole, other ticks"].append(dt)
            done[name] = min(i0 + block, ticks)
        order.reverse()
    answer = brains["whole"].infer("fast_loop", raw[0], session="robot")
    status = brains["whole"].status()
    model = MidLoopNumpy.from_checkpoint(mid)
    forms = {name: summary_ms(v) for name, v in lat.items()}
    forms.update(mid_forms(model, max(200, ticks // 10)))
    return {"forms": forms, "mid_loop": repr(model), "vqvae": status["vqvae"]["version"],
            "fields": sorted(answer), "every": status["mid_loop"]["grid_step_s"] / CONTROL_PERIOD_S}


def mid_forms(model, n: int) -> dict[str, dict[str, float]]:
    """The Mid Loop's prediction from the last K points: the window form against re-stepping K points."""
    rng = np.random.default_rng(1)
    k, g = model.window_k, model.groups
    rows = model.rows(rng.integers(0, model.n_codes, (k, g)))
    acts = rng.normal(0, 1, (k, model.act_dim)).astype(np.float32)
    points = list(rows - model.rows(np.zeros(model.groups, np.int64)))  # group-local codes, what predict() reads
    ahead_name, last_name = "mid_loop window ahead, K-1 points (all stages)", "mid_loop last point from them (predict)"
    lat: dict[str, list[float]] = {"mid_loop window form (forward, K points)": [],
                                   "mid_loop re-stepping K points (step x K)": [], ahead_name: [], last_name: []}
    for _ in range(n):
        t0 = time.perf_counter()
        model.prediction(model.log_probs(model.forward(rows, acts, last_only=True)[-1]))
        t1 = time.perf_counter()
        state = model.init_state()
        for i in range(k):
            logits, state = model.step(rows[i], acts[i], state)
        model.prediction(model.log_probs(logits))
        t2 = time.perf_counter()
        # what BrainService runs: the window but its last point on the ticks between grid points
        # (window_ahead, then ahead_step a stage a tick), the grid point its own point alone
        ahead = model.window_ahead(points[:-1], acts[:-1])
        while not model.ahead_step(ahead):
            pass
        t3 = time.perf_counter()
        model.predict(points, acts, ahead)
        t4 = time.perf_counter()
        lat["mid_loop window form (forward, K points)"].append(t1 - t0)
        lat["mid_loop re-stepping K points (step x K)"].append(t2 - t1)
        lat[ahead_name].append(t3 - t2)
        lat[last_name].append(t4 - t3)
    return {name: summary_ms(v) for name, v in lat.items()}


# -- 6. the full answer from a camera frame ---------------------------------------------------------

def camera_models(root: Path, side: int, seed: int = 0) -> dict[str, Path]:
    """Checkpoints with random weights, written as training writes them: a grid VQ-VAE (its codebook
    from encoder outputs, as training's first step), a fast_loop and a default-size grid Mid Loop
    over it."""
    import torch

    from hope_models.checkpoints import save_checkpoint
    from hope_models.components.build import build_component
    from hope_models.data.features import FeatureField, FeatureGroup, FeatureSpec, FrameFeature

    torch.manual_seed(seed)
    joints = FeatureGroup([FeatureField("observation.robot_state.joint_positions", 2),
                           FeatureField("observation.robot_state.joint_velocities", 2)], [0.0] * 4, [1.0] * 4)
    act = FeatureGroup([FeatureField("action.command", 2)], [0.0, 0.0], [1.0, 1.0])
    spec = FeatureSpec(joints, act, FrameFeature("observation.camera", (side, side, 3), source="blob"))

    def save(name: str, comp) -> Path:
        return save_checkpoint(root / name, 1, model_state=comp.model.state_dict(), config=comp.config(),
                               state_tensors={}, state={})

    out = {}
    for name in ("vq", "vq_other"):
        vq = build_component("vqvae", spec, model_config=FRAME_VQ)
        with torch.no_grad():
            vq.model(torch.from_numpy(moving_frames(16, seed + len(out), side)), init_codebook=True)
        out[name] = save(f"cam-{name}", vq)
    out["fast"] = save("cam-fast", build_component("fast_loop", spec, vqvae_dir=out["vq"]))
    out["mid_grid"] = save("cam-mid", build_component("mid_loop", spec, vqvae_dir=out["vq"]))
    return out


def frame_answer(root: Path, ticks: int, side: int = 64, block: int = 250) -> dict[str, Any]:
    import base64
    import io

    from PIL import Image

    from hope_models.components.fast_loop.numpy_form import FastLoopNumpy
    from hope_models.runtime.brain_service import BrainService

    ckpts = camera_models(root / "camera", side)
    setups = {"frame": {"vqvae": ckpts["vq"], "fast_loop": ckpts["fast"]},
              "frame, tokenizer's VQ-VAE another (two encodes)": {"vqvae": ckpts["vq_other"], "fast_loop": ckpts["fast"]},
              "frame, whole brain": {"vqvae": ckpts["vq"], "fast_loop": ckpts["fast"], "mid_loop": ckpts["mid_grid"]}}
    brains = {}
    for i, (name, promoted) in enumerate(setups.items()):
        home = root / f"home-frame-{i}"
        for component, ckpt in promoted.items():
            write_pointer(home, ckpt, component=component)
        brains[name] = BrainService(home, components=tuple(promoted))
        brains[name].check_now()
    frames = moving_frames(1024, 7, side)

    def encoded(img: np.ndarray, fmt: str) -> str:
        buf = io.BytesIO()
        Image.fromarray(img).save(buf, fmt, **({"quality": 90} if fmt == "JPEG" else {}))
        return base64.b64encode(buf.getvalue()).decode()

    raw = [{"encoding": "raw", "shape": [side, side, 3], "data": base64.b64encode(f.tobytes()).decode()} for f in frames]
    png = [encoded(f, "PNG") for f in frames]
    jpeg = [encoded(f, "JPEG") for f in frames]
    joints = np.random.default_rng(0).normal(0, 1, (1024, 4)).tolist()
    fast = FastLoopNumpy.from_checkpoint(ckpts["fast"])
    state = [fast.init_state()]
    codes = fast.frame_codes(frames)

    def infer(name: str, sent: list) -> Callable[[int], None]:
        brain = brains[name]
        return lambda i: brain.infer("fast_loop", joints[i & 1023], session="robot", frame=sent[i & 1023])

    def tick_alone(i: int) -> None:
        _, state[0] = fast.tick(fast.normalise(np.asarray(joints[i & 1023])), state[0], codes[i & 1023])

    forms: dict[str, Callable[[int], None]] = {
        "frame answer, raw frame (encode + fast_loop)": infer("frame", raw),
        "frame answer, base64 PNG": infer("frame", png),
        "frame answer, base64 JPEG": infer("frame", jpeg),
        "frame answer, two VQ-VAEs (two encodes)": infer("frame, tokenizer's VQ-VAE another (two encodes)", raw),
        WHOLE_FRAME: infer("frame, whole brain", raw),
        "frame encode alone (VQVAENumpy.codes)": lambda i: fast.frame_codes(frames[i & 1023]),
        "fast_loop tick alone (codes given)": tick_alone,
    }
    lat: dict[str, list[float]] = {name: [] for name in forms}
    points: list[float] = []  # the whole brain's grid-point ticks (its session's tick 0, 5, 10, ...)
    cpu: list[float] = []
    cpu_whole: list[float] = []
    for fn in forms.values():  # warm-up (50 ticks: the whole brain's session then starts at a grid point)
        for i in range(50):
            fn(i)
    perf = time.perf_counter
    first = next(iter(forms))
    for start in range(0, ticks, block):  # interleaved blocks: machine noise falls on all alike
        for name, fn in forms.items():
            out = lat[name]
            for i in range(start, min(start + block, ticks)):
                c0, t0 = time.thread_time(), perf()
                fn(i)
                out.append(perf() - t0)
                if name == first:
                    cpu.append(time.thread_time() - c0)
                elif name == WHOLE_FRAME:
                    cpu_whole.append(time.thread_time() - c0)
                    if i % 5 == 0:
                        points.append(out[-1])
    res = {name: summary_ms(v) for name, v in lat.items()}
    res[WHOLE_FRAME + ", grid-point ticks"] = summary_ms(points)
    res[WHOLE_FRAME + ": thread CPU time"] = summary_ms(cpu_whole)
    res["frame answer, raw frame: thread CPU time"] = summary_ms(cpu)
    answer = brains["frame"].infer("fast_loop", joints[0], session="robot", frame=raw[0])
    whole = brains["frame, whole brain"].infer("fast_loop", joints[0], session="robot", frame=raw[0])
    assert whole["surprise"] is not None and whole["prediction"] is not None, whole  # the grid Mid Loop answered
    mid = brains["frame, whole brain"].status()["mid_loop"]
    return {"forms": res, "side": side, "vqvae": FRAME_VQ, "fast_loop": repr(fast), "fields": sorted(answer),
            "mid_loop": f"grid Mid Loop {mid['grid']} cells x {mid['n_codes']} codes, K={mid['window_k']}, "
                        f"horizons {mid['horizons']}, grid step {mid['grid_step_s']:g} s",
            "code_len": len(answer["code"]), "png_bytes": int(np.mean([len(v) * 3 // 4 for v in png])),
            "jpeg_bytes": int(np.mean([len(v) * 3 // 4 for v in jpeg]))}


# -- main ------------------------------------------------------------------------------------------------

def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ticks", type=int, default=4000, help="ticks per form (default 4000)")
    ap.add_argument("--swaps", type=int, default=6, help="pointer rewrites under load (default 6)")
    ap.add_argument("--closures", type=int, default=2, help="runs trained, promoted and first used (default 2)")
    ap.add_argument("--train-steps", type=int, default=60, help="steps of each trained run (default 60)")
    ap.add_argument("--k-scaling", action="store_true", help="also time a K=20 fast_loop")
    ap.add_argument("--out", type=Path, default=None, help="work dir (default a temp dir)")
    ap.add_argument("--json", action="store_true", help="print the result as JSON")
    ap.add_argument("--whole-only", action="store_true", help="skip the loop-closure runs (section 3)")
    ap.add_argument("--closure-only", action="store_true", help="only the loop-closure runs (section 3)")
    ap.add_argument("--frame-only", action="store_true", help="only the camera frame's answer (section 6)")
    ap.add_argument("--frame-side", type=int, default=64, help="the camera frame's side (default 64; 96 allowed)")
    args = ap.parse_args()
    import torch

    torch.set_num_threads(1)
    root = args.out or Path(tempfile.mkdtemp(prefix="hope-bench-inference-"))
    root.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    if args.frame_only:
        result: dict[str, Any] = {"frame": frame_answer(root, args.ticks, args.frame_side)}
        result["elapsed_s"] = round(time.perf_counter() - started, 1)
        result["targets"] = frame_targets(result)
        if args.json:
            print(json.dumps(result, indent=1))
        else:
            report_frame(result)
            report_targets(result)
        return 0
    data = make_dataset(root)
    if args.closure_only:
        result = {"loop_closure": loop_closure(root, data, args.closures, args.train_steps)}
        print(json.dumps(result, indent=1) if args.json else "")
        if not args.json:
            report_closure(result)
        return 0
    cache = root / "cache"
    ckpt_b = train_run(data, root / "runs" / "main", cache, args.train_steps, args.train_steps // 2)
    ckpt_a = ckpt_b.parent / f"{args.train_steps // 2:08d}"
    result = {"tick": {"K=5": tick_latency(ckpt_b, root / "home-tick", args.ticks)}}
    if args.k_scaling:
        ck20 = train_run(data, root / "runs" / "k20", cache, 20, 20, {"window": {"k": 20, "duration_s": 0.1}})
        result["tick"]["K=20"] = tick_latency(ck20, root / "home-tick20", args.ticks)
    result["swap"] = swap_pause(ckpt_a, ckpt_b, root / "home-swap", args.swaps)
    result["rss"] = service_rss(root / "home-swap")
    result["whole"] = whole_answer(root, data, ckpt_b, args.ticks)
    result["frame"] = frame_answer(root, args.ticks, args.frame_side)
    if not args.whole_only:
        result["loop_closure"] = loop_closure(root, data, args.closures, args.train_steps)
    result["elapsed_s"] = round(time.perf_counter() - started, 1)
    result["targets"] = targets(result) + frame_targets(result)
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        report(result)
    return 0


def targets(r: dict[str, Any]) -> list[dict[str, Any]]:
    forms = r["tick"]["K=5"]["forms"]
    rec = forms["numpy recurrent (FastLoopNumpyAct.act)"]
    svc = forms["BrainService.infer (session)"]
    out = []
    for name, f in (("FastLoopNumpyAct.act", rec), ("BrainService.infer", svc)):
        out.append({"target": f"{name} p99 < {TARGET_P99_MS:g} ms", "value": f"{f['p99_ms']:.3f} ms",
                    "pass": f["p99_ms"] < TARGET_P99_MS})
    for other in ("torch window re-run (FastLoop.forward)", "numpy window re-run (FastLoopNumpy.forward)"):
        for q in ("p50_ms", "p99_ms"):
            ratio = forms[other][q] / rec[q]
            out.append({"target": f"recurrent >= {TARGET_SPEEDUP:g}x faster than the {other.split(' (')[0]} ({q[:3]})",
                        "value": f"{ratio:.1f}x", "pass": ratio >= TARGET_SPEEDUP})
    whole = r["whole"]["forms"]["whole"]
    out.append({"target": f"full answer (vqvae + fast_loop + mid_loop) p99 <= {TARGET_WHOLE_P99_MS:g} ms",
                "value": f"{whole['p99_ms']:.3f} ms", "pass": whole["p99_ms"] <= TARGET_WHOLE_P99_MS})
    sw = r["swap"]
    out.append({"target": f"swap: p99 during swaps <= {TARGET_SWAP_RATIO:g}x normal, 0 failures, one switch per swap",
                "value": f"{sw['p99_ratio']}x, {sw['failures']} failures, {sw['version_switches']}/{sw['swaps']}",
                "pass": sw["p99_ratio"] <= TARGET_SWAP_RATIO and sw["failures"] == 0
                and sw["version_switches"] == sw["swaps"]})
    return out


def frame_targets(r: dict[str, Any]) -> list[dict[str, Any]]:
    side = r["frame"]["side"]
    out = []
    for name in ("frame answer, raw frame (encode + fast_loop)", WHOLE_FRAME):
        f = r["frame"]["forms"][name]
        out.append({"target": f"{name} at {side}x{side} p99 <= {TARGET_FRAME_P99_MS:g} ms",
                    "value": f"{f['p99_ms']:.3f} ms", "pass": f["p99_ms"] <= TARGET_FRAME_P99_MS})
    return out


def report_frame(r: dict[str, Any]) -> None:
    fr = r["frame"]
    print(f"\nThe answer from a camera frame ({fr['side']}x{fr['side']}, one session): {fr['fast_loop']}; "
          f"{fr['mid_loop']}; tokenizer "
          f"{fr['vqvae']} ({fr['code_len']} codes); a frame is ~{fr['png_bytes']} B as PNG, ~{fr['jpeg_bytes']} B as "
          f"JPEG; answer fields {', '.join(fr['fields'])}")
    print(f"  {'form':78s} {'p50 ms':>8s} {'p99 ms':>8s} {'mean ms':>8s} {'max ms':>8s}")
    for name, f in fr["forms"].items():
        print(f"  {name:78s} {f['p50_ms']:8.3f} {f['p99_ms']:8.3f} {f['mean_ms']:8.3f} {f['max_ms']:8.2f}")


def report_targets(r: dict[str, Any]) -> None:
    print("\nTargets:")
    for t in r["targets"]:
        print(f"  {'PASS' if t['pass'] else 'MISS'}  {t['target']}: {t['value']}")
    print(f"\nelapsed {r['elapsed_s']} s")


def report(r: dict[str, Any]) -> None:
    for key, t in r["tick"].items():
        print(f"\nOne tick, batch 1, {key}: {t['model']} (d_model {t['d_model']}, d_state {t['d_state']})")
        print(f"  {'form':46s} {'p50 ms':>8s} {'p99 ms':>8s} {'mean ms':>8s} {'max ms':>8s}")
        for name, f in t["forms"].items():
            print(f"  {name:46s} {f['p50_ms']:8.3f} {f['p99_ms']:8.3f} {f['mean_ms']:8.3f} {f['max_ms']:8.2f}")
    sw = r["swap"]
    print(f"\nSwap pause: {sw['requests']} requests, {sw['failures']} failed, {sw['swaps']} swaps, "
          f"{sw['version_switches']} version switches; pointer write -> serving the new version "
          f"median {sw['pointer_to_swap_ms']['median']} ms, max {sw['pointer_to_swap_ms']['max']} ms")
    for name in ("normal", "during_swaps"):
        f = sw[name]
        print(f"  {name:14s} n={f['n']:7d}  p50 {f['p50_ms']:.3f} ms  p99 {f['p99_ms']:.3f} ms  "
              f"max {f['max_ms']:.2f} ms")
    print(f"  p99 ratio during/normal: {sw['p99_ratio']}x")
    rss = r["rss"]
    print(f"\nRSS of a process with BrainService serving: {rss['with_brain_mb']} MB (bare python + psutil "
          f"before the import: {rss['python_mb']} MB); torch imported: {rss['torch_imported']}")
    w = r["whole"]
    print(f"\nThe full answer, one session at 50 Hz ticks (a grid point every {w['every']:g} ticks): {w['mid_loop']}, "
          f"vqvae {w['vqvae']}; answer fields {', '.join(w['fields'])}")
    print(f"  {'form':46s} {'p50 ms':>8s} {'p99 ms':>8s} {'mean ms':>8s} {'max ms':>8s}")
    for name, f in w["forms"].items():
        print(f"  {name:46s} {f['p50_ms']:8.3f} {f['p99_ms']:8.3f} {f['mean_ms']:8.3f} {f['max_ms']:8.2f}")
    report_closure(r)
    report_frame(r)
    report_targets(r)


def report_closure(r: dict[str, Any]) -> None:
    print("\nLoop closure (run completed -> first inference on its weights), 50 Hz robot loop; the gate in the "
          "process that trained (warm: the worker child) or in a fresh `promote` child (child: auto-promotion's):")
    for c in r.get("loop_closure", {}).get("closures", []):
        if c.get("refused"):
            print(f"  {c['version']:28s} refused by the gate: {'; '.join(c['refused'])}")
            continue
        print(f"  {c['gate']:5s} {c['version']:28s} loop_closure_s {c['loop_closure_s']}  (completed -> gate done "
              f"{c['promote_process_s']} s, completed -> new weights loaded {c['finished_to_loaded_s']} s, loaded -> "
              f"first inference {c['loaded_to_first_inference_s']} s; gate compared with a promoted model: "
              f"{c['compared_with_promoted']})")


if __name__ == "__main__":
    sys.exit(main())
