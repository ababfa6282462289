"""Why the fast_loop's recurrent tick is not 5x faster than re-running its window in NumPy at K=5.

At batch 1 both forms cost their matrix products (streaming the same ~1 MB of weights once per
call: a 5-row product costs little more than a 1-row one) plus NumPy's dispatch of every array
operation. This measures, interleaved in blocks on one thread:
- the tick (FastLoopNumpyAct.act, what section 1 of bench/inference.py times) and the window
  re-run (FastLoopNumpy.forward over the last K normalised observations, + denormalise);
- each form's matrix products alone, with its real weights and shapes (the tick: 8 one-row
  products; the window: its K-row and 1-row products);
- one element-wise NumPy op on a d_model vector (the price of any further op);
and prints the floor of the tick (its products + its 37 other array ops at that price) and the ratio the
window re-run would have over a tick that cost only its products: the best any NumPy tick can do.

    .venv/bin/python bench/tick_anatomy.py                # trains the bench's fast_loop (~10 s)
    .venv/bin/python bench/tick_anatomy.py --ckpt runs/x/checkpoints/00000060 --json

It prints figures; it is not a test.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))  # inference.py: the bench fast_loop

# act() + _core() per tick, counted in the source: 54 array operations, of which 8 matrix products
# and 9 views (slices, indexing: ~0.1 us each), the other 37 element-wise ops, reductions and copies
TICK_ELEMENTWISE = 37


def forms(ckpt: Path) -> dict[str, Callable[[], object]]:
    from hope_models.components.fast_loop.numpy_act import FastLoopNumpyAct

    m = FastLoopNumpyAct.from_checkpoint(ckpt)
    k, rng = m.window_k, np.random.default_rng(0)
    x = rng.normal(0, 1, m.obs_dim)
    window = m.normalise(rng.normal(0, 1, (1, k, m.obs_dim)))
    state = m.init_state()
    flat = m._flat
    e_w, gu1, out1, vd, c_t, gu2, out2, a_w = (m._e_w_raw, flat[5], flat[8], flat[10], flat[15], flat[16], flat[19],
                                               m._a_w_raw)
    v = {w.shape[0]: rng.normal(0, 1, w.shape[0]).astype(np.float32) for w in (e_w, gu1, out1, vd, c_t, gu2, out2)}
    x32, a64 = x.astype(np.float32), rng.normal(0, 1, a_w.shape[0])
    rows = {n: rng.normal(0, 1, (1, k, n)).astype(np.float32) for n in (m.obs_dim, m.d_model, out1.shape[0])}
    enc, head = m._enc, m._head
    bg, c_plain, out_w = m._bg_t, m._c_t, m._out.w_t
    one = {n: rng.normal(0, 1, (1, n)).astype(np.float32) for n in (m.d_model, m.d_state, out1.shape[0])}

    def tick_products():
        x32.dot(e_w), v[gu1.shape[0]].dot(gu1), v[out1.shape[0]].dot(out1), v[vd.shape[0]].dot(vd)
        v[c_t.shape[0]].dot(c_t), v[gu2.shape[0]].dot(gu2), v[out2.shape[0]].dot(out2), a64.dot(a_w)

    def window_products():
        rows[m.obs_dim] @ m._obs_in.w_t, rows[m.d_model] @ enc.gu_w, rows[out1.shape[0]] @ enc.out_w
        rows[m.d_model] @ bg, one[m.d_state].dot(c_plain), one[m.d_model].dot(head.gu_w)
        one[out1.shape[0]].dot(head.out_w), one[m.d_model].dot(out_w)

    vec = rng.normal(0, 1, m.d_model).astype(np.float32)
    bias = rng.normal(0, 1, m.d_model).astype(np.float32)

    def one_op():
        vec.__iadd__(bias)
        vec.__isub__(bias)

    return {"tick (act)": lambda: m.act(x, state),
            "window re-run (forward K)": lambda: m.denormalise(m.forward(window)[0]),
            "tick's 8 products alone": tick_products,
            "window's products alone": window_products,
            "one element-wise op, x2": one_op}


def measure(fns: dict[str, Callable[[], object]], n: int, block: int = 200) -> dict[str, float]:
    lat: dict[str, list[float]] = {name: [] for name in fns}
    for fn in fns.values():
        for _ in range(50):
            fn()
    perf = time.perf_counter
    for _ in range(0, n, block):
        for name, fn in fns.items():
            out = lat[name]
            for _ in range(block):
                t0 = perf()
                fn()
                out.append(perf() - t0)
    return {name: float(np.percentile(v, 50)) * 1e6 for name, v in lat.items()}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ckpt", type=Path, default=None, help="a fast_loop checkpoint (default: train the bench's)")
    ap.add_argument("--n", type=int, default=20000, help="calls per form (default 20000)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    ckpt = args.ckpt
    if ckpt is None:
        import inference

        root = Path(tempfile.mkdtemp(prefix="hope-bench-anatomy-"))
        ckpt = inference.train_run(inference.make_dataset(root), root / "runs" / "main", root / "cache", 60, 60)
    p50 = measure(forms(ckpt), args.n)
    tick, window = p50["tick (act)"], p50["window re-run (forward K)"]
    op = p50["one element-wise op, x2"] / 2
    floor = p50["tick's 8 products alone"] + TICK_ELEMENTWISE * op
    res = {"p50_us": {k: round(v, 2) for k, v in p50.items()},
           "ratio window / tick": round(window / tick, 2),
           "tick floor (products + ops at the one-op price), us": round(floor, 2),
           "ratio window / tick floor": round(window / floor, 2),
           "ratio window / tick's products alone (no dispatch at all)": round(window / p50["tick's 8 products alone"], 2)}
    if args.json:
        print(json.dumps(res, indent=1))
    else:
        for k, v in res["p50_us"].items():
            print(f"  {k:34s} p50 {v:8.2f} us")
        for k, v in res.items():
            if k != "p50_us":
                print(f"  {k}: {v}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
