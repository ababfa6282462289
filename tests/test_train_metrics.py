"""metrics.jsonl + crash-safe metrics.mcap + the event callback; resume segments; the summary."""
import json
import os
import signal
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from mcap.exceptions import EndOfFile
from mcap.reader import NonSeekingReader, make_reader

from hope_models.train.metrics import (
    EVENT_SCHEMA, METRIC_SCHEMA, MetricsLog, convergence_summary, load_losses, mcap_segments,
    read_jsonl, read_mcap_records, read_metrics,
)

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def stream_messages(path):
    """Every message mcap's own streaming reader gets out of a file, finished or cut short."""
    out = []
    with open(path, "rb") as f:
        try:
            for schema, channel, message in NonSeekingReader(f).iter_messages(log_time_order=False):
                out.append((channel.topic, schema.name, schema.encoding, channel.message_encoding,
                            json.loads(message.data)))
        except EndOfFile:  # no footer: the writer was killed
            pass
    return out


def test_log_and_event_go_to_jsonl_mcap_and_the_callback(tmp_path):
    seen = []
    with MetricsLog(tmp_path, emit=lambda kind, payload: seen.append((kind, payload))) as m:
        m.log(1, {"loss": 2.5, "lr": 1e-3, "grad_norm": np.float32(0.5), "throttle_level": "normal"})
        m.event("throttle", {"level": "slow", "temp_c": 78.0})
        m.log(2, {"loss": float("nan"), "rss_mb": 300})
    lines = read_jsonl(tmp_path / "metrics.jsonl")
    assert [r["type"] for r in lines] == ["metric", "event", "metric"]
    assert lines[0]["loss"] == 2.5 and lines[0]["grad_norm"] == 0.5 and lines[0]["step"] == 1
    assert lines[1] == {"type": "event", "kind": "throttle", "wall_time": lines[1]["wall_time"],
                        "payload": {"level": "slow", "temp_c": 78.0}}
    assert lines[2]["loss"] is None  # JSON has no NaN
    assert [k for k, _ in seen] == ["metric", "throttle", "metric"]
    assert seen[1][1] == {"level": "slow", "temp_c": 78.0} and seen[0][1]["loss"] == 2.5

    # A finished segment opens with mcap's seeking reader, schemas and encodings as Foxglove wants.
    with open(tmp_path / "metrics.mcap", "rb") as f:
        got = [(c.topic, s.name, s.encoding, c.message_encoding, json.loads(msg.data))
               for s, c, msg in make_reader(f).iter_messages(log_time_order=False)]
    assert [g[0] for g in got] == ["/metrics", "/events", "/metrics"]
    assert {g[2] for g in got} == {"jsonschema"} and {g[3] for g in got} == {"json"}
    assert [g[4] for g in got] == lines
    assert json.loads(json.dumps(METRIC_SCHEMA))["required"] == ["type", "step", "wall_time"]
    records, complete = read_mcap_records(tmp_path / "metrics.mcap")
    assert complete and [r for _, r in records] == lines
    assert "payload" in EVENT_SCHEMA["required"]


def test_reserved_names_and_bad_kinds_are_refused(tmp_path):
    with MetricsLog(tmp_path) as m:
        with pytest.raises(ValueError, match="reserved"):
            m.log(1, {"step": 3})
        with pytest.raises(ValueError, match="kind"):
            m.event("", {})


WRITER = textwrap.dedent("""
    import sys
    sys.path.insert(0, {repo!r})
    from hope_models.train.metrics import MetricsLog
    m = MetricsLog(sys.argv[1])
    step = 0
    while True:  # until killed
        m.log(step, {{"loss": 1.0 / (step + 1), "lr": 0.001, "note": "x" * 40}})
        if step % 7 == 0:
            m.event("checkpoint", {{"step": step}})
        print(step, flush=True)
        step += 1
""")


def test_sigkill_mid_run_leaves_a_readable_mcap_and_resume_starts_a_new_segment(tmp_path):
    script = tmp_path / "writer.py"
    script.write_text(WRITER.format(repo=REPO))
    run = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, str(script), str(run)], stdout=subprocess.PIPE, text=True)
    acknowledged = -1
    try:
        for line in proc.stdout:  # each printed step was logged (and flushed) before it was printed
            acknowledged = int(line)
            if acknowledged >= 300:
                break
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL and acknowledged >= 300

    msgs = stream_messages(run / "metrics.mcap")  # mcap's reader, no footer in the file
    steps = [r["step"] for topic, *_, r in msgs if topic == "/metrics"]
    assert steps == list(range(len(steps)))  # nothing lost or garbled before the last flush
    assert len(steps) >= acknowledged + 1
    assert all(name == "hope.train.Metric" for topic, name, *_ in msgs if topic == "/metrics")
    records, complete = read_mcap_records(run / "metrics.mcap")
    assert not complete and [r["step"] for t, r in records if t == "/metrics"] == steps
    jsonl_steps = [r["step"] for r in read_jsonl(run / "metrics.jsonl") if r["type"] == "metric"]
    assert jsonl_steps[: acknowledged + 1] == list(range(acknowledged + 1))

    # Resume: the old segment is left alone, a new one is started, the JSONL is appended to.
    before = (run / "metrics.mcap").read_bytes()
    with MetricsLog(run) as m:
        assert m.mcap_path.name == "metrics.1.mcap"
        m.event("resume", {"step": 100})
        for s in range(101, 104):
            m.log(s, {"loss": 0.01})
    assert (run / "metrics.mcap").read_bytes() == before
    assert [p.name for p in mcap_segments(run)] == ["metrics.mcap", "metrics.1.mcap"]
    second = stream_messages(run / "metrics.1.mcap")
    assert [r.get("step") for t, *_, r in second if t == "/metrics"] == [101, 102, 103]
    # The timeline drops the first attempt's steps after the resume point.
    losses = load_losses(run)
    assert [s for s, _ in losses] == list(range(0, 101)) + [101, 102, 103]
    assert losses[-1] == (103, 0.01)


def test_a_partial_last_jsonl_line_is_cut_before_appending(tmp_path):
    (tmp_path / "metrics.jsonl").write_text('{"type":"metric","step":1,"wall_time":1,"loss":1}\n{"type":"met')
    with MetricsLog(tmp_path) as m:
        m.log(2, {"loss": 0.5})
    text = (tmp_path / "metrics.jsonl").read_text()
    assert text.count("\n") == 2 and '"met\n' not in text
    assert [r["step"] for r in read_jsonl(tmp_path / "metrics.jsonl")] == [1, 2]


def test_segments_number_on(tmp_path):
    names = []
    for _ in range(3):
        with MetricsLog(tmp_path) as m:
            names.append(m.mcap_path.name)
    assert names == ["metrics.mcap", "metrics.1.mcap", "metrics.2.mcap"]
    (tmp_path / "metrics.10.mcap").write_bytes(b"")
    assert [p.name for p in mcap_segments(tmp_path)][-1] == "metrics.10.mcap"
    with MetricsLog(tmp_path) as m:
        assert m.mcap_path.name == "metrics.11.mcap"


def test_read_metrics_on_a_missing_run_is_empty(tmp_path):
    assert read_metrics(tmp_path / "none") == []


def test_convergence_summary_against_numpy():
    rng = np.random.default_rng(0)
    steps = np.arange(0, 200, 2)
    loss = 3.0 * np.exp(-steps / 80) + rng.normal(0, 0.01, steps.size)
    s = convergence_summary(list(zip(steps.tolist(), loss.tolist())))
    assert s["first10_mean"] == pytest.approx(loss[:10].mean())
    assert s["last10_mean"] == pytest.approx(loss[-10:].mean())
    assert s["ratio"] == pytest.approx(loss[-10:].mean() / loss[:10].mean())
    assert s["slope"] == pytest.approx(np.polyfit(steps, loss, 1)[0])
    assert s["slope"] < 0 and s["n"] == 100


def test_convergence_summary_edge_cases():
    assert convergence_summary([]) == {"first10_mean": None, "last10_mean": None, "ratio": None,
                                       "slope": None, "n": 0}
    one = convergence_summary([(5, 2.0)])
    assert one["first10_mean"] == one["last10_mean"] == 2.0 and one["slope"] is None
    s = convergence_summary([(1, 4.0), (2, float("nan")), (3, 2.0), (4, float("inf"))])
    assert s["n"] == 2 and s["slope"] == pytest.approx(-1.0)
    unsorted = convergence_summary([(3, 1.0), (1, 3.0), (2, 2.0)])
    assert unsorted["slope"] == pytest.approx(-1.0)


def test_the_train_command_prints_a_one_step_run():
    """One logged loss has no slope: the summary line says so instead of failing to format it."""
    from types import SimpleNamespace

    from hope_models.cli.train import format_result

    result = SimpleNamespace(outcome="completed", component="vqvae", steps=1, total_steps=1, resumed_from=None,
                             first_loss=0.7, final_loss=0.7, summary={**convergence_summary([(1, 0.7)]), "val": {}},
                             checkpoint="/x/00000001", peak_rss_mb=300.0, message="")
    text = format_result(result, 3072)
    assert "slope -/step" in text and "ratio 1.000" in text and "checkpoint /x/00000001" in text
