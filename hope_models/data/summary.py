"""What a dataset holds once compiled: the figures `run_trainer.py dataset` and examples/data_tour.py print."""
from __future__ import annotations

import statistics
from collections import Counter
from pathlib import Path
from typing import Any

from hope_models.data.cache import load_or_build
from hope_models.data.sampler import validation_mask

DEFAULT_VAL_FRACTION = 0.1


def _rate_label(rate: float | None) -> str:
    if rate is None:
        return "single step"
    return f"{round(rate):d} Hz" if rate >= 1.5 else f"{rate:.2g} Hz"


def summarise_dataset(dataset_dir: str | Path, cache_root: str | Path, spec_path: str | Path | None = None,
                      val_fraction: float = DEFAULT_VAL_FRACTION) -> dict[str, Any]:
    """Infer or load the spec, build or reuse the cache, and describe the result as a JSON-able dict.

    Raises CacheError / FeatureSpecError (ValueErrors with a message naming the file) when the
    dataset cannot be compiled at all; episodes that merely do not fit are listed under "excluded".
    """
    cache, info = load_or_build(dataset_dir, cache_root, spec_path)
    eps = cache.episodes
    durations = [e["duration_s"] for e in eps]
    spec = cache.spec
    n_val = int(validation_mask([e["episode_id"] for e in eps], val_fraction).sum())
    return {
        "dataset_dir": str(Path(dataset_dir).resolve()),
        "cache_path": str(info.path),
        "fingerprint": info.fingerprint,
        "data_fingerprint": info.data_fingerprint,
        "reused": info.reused,
        "build_seconds": round(info.build_seconds, 3),
        "original_build_seconds": cache.manifest.get("build_seconds"),
        "fingerprint_seconds": round(info.fingerprint_seconds, 3),
        "cache_notes": info.notes,
        "episodes": cache.n_episodes,
        "steps": cache.n_steps,
        "imagined_episodes": int(cache.imagined.sum()),
        "rates": dict(sorted(Counter(_rate_label(e["rate_hz"]) for e in eps).items())),
        "duration_s": {
            "total": round(sum(durations), 3),
            "min": round(min(durations), 3),
            "median": round(statistics.median(durations), 3),
            "max": round(max(durations), 3),
        },
        "obs_dim": spec.obs_dim,
        "act_dim": spec.act_dim,
        "observation_fields": [{"path": f.path, "size": f.size} for f in spec.observation.fields],
        "action_fields": [{"path": f.path, "size": f.size} for f in spec.action.fields],
        "frame": None if spec.frame is None else spec.frame.to_json_obj(),
        "cameras": [_camera(cache, name, tokenizer=name == "frames") for name in cache.manifest["arrays"]
                    if name == "frames" or name.startswith("camera.")],
        "spec_notes": spec.notes,
        "split": {"val_fraction": val_fraction, "train_episodes": cache.n_episodes - n_val, "val_episodes": n_val},
        "excluded": cache.manifest["excluded"],
        "access_mode": cache.mode,
    }


def _camera(cache, array: str, tokenizer: bool) -> dict[str, Any]:
    desc = cache.manifest["arrays"][array]
    path = desc.get("path") or (cache.spec.frame.path if cache.spec.frame is not None else array)
    return {"name": path.removeprefix("observation."), "path": path, "kind": desc.get("kind", "rgb"),
            "shape": desc["shape"][1:], "frames": desc["shape"][0], "steps": cache.n_steps,
            "decoded_from": desc.get("decoded_from", {}), "tokenizer": tokenizer}


def _camera_line(c: dict[str, Any]) -> str:
    """"egocentric_video: 1200/1200 frames, JPEG 480x640 -> 64x64 (the tokenizer reads it)"."""
    size = f"{c['shape'][0]}x{c['shape'][1]}"
    sources = ", ".join(f"{k} -> {size}" + (f" ({n})" if len(c["decoded_from"]) > 1 else "")
                        for k, n in c["decoded_from"].items()) or size
    use = ("the tokenizer reads it" if c["tokenizer"] else
           "depth in metres, stored; no component reads depth yet" if c["kind"] == "depth" else
           "stored; the tokenizer reads another camera")
    return f"{c['name']}: {c['frames']}/{c['steps']} frames, {sources} ({use})"


def format_summary(s: dict[str, Any]) -> str:
    d = s["duration_s"]
    fields = lambda fs: ", ".join(f"{f['path']}[{f['size']}]" for f in fs)  # noqa: E731
    lines = [
        f"dataset      {s['dataset_dir']}",
        f"episodes     {s['episodes']} ({s['imagined_episodes']} imagined; split train {s['split']['train_episodes']}"
        f" / val {s['split']['val_episodes']})",
        f"steps        {s['steps']}",
        "rates        " + ", ".join(f"{k}: {v}" for k, v in s["rates"].items()),
        f"durations    total {d['total']:.1f} s; per episode min {d['min']:.2f} / median {d['median']:.2f} "
        f"/ max {d['max']:.2f} s",
        f"observation  {s['obs_dim']} dims: {fields(s['observation_fields'])}",
        f"action       {s['act_dim']} dims: {fields(s['action_fields'])}",
        *(["camera       none"] if not s["cameras"] else [f"camera       {_camera_line(c)}" for c in s["cameras"]]),
        f"cache        {s['cache_path']} ({'reused' if s['reused'] else 'built'}"
        + ("" if s["reused"] else f" in {s['build_seconds']:.1f} s") + f"; access {s['access_mode']})",
        f"fingerprint  {s['fingerprint']} (data {s['data_fingerprint'][:16]}..., hashed in "
        f"{s['fingerprint_seconds']:.1f} s)",
    ]
    for note in s["cache_notes"]:
        lines.append(f"note         {note}")
    for note in s["spec_notes"]:
        lines.append(f"spec note    {note}")
    lines.append(f"excluded     {len(s['excluded'])} episode(s)" + (":" if s["excluded"] else ""))
    for e in s["excluded"]:
        lines.append(f"  - {e['episode_id']}: {e['reason']}")
    return "\n".join(lines)
