"""The bad-input table of the API, generated: every POST endpoint and the query parameters of the
GETs, field by field, against the contract "bad input gets a 4xx with a message naming the field,
never a 500, and nothing is written".

Each case is sent through Flask's test client (test_api.App, no BrainService: every case is
refused before it would be needed) and must get a 4xx, a JSON body whose "error" is a non-empty
message (naming the field, where the case is about one field), no new or changed run, event or
model row, and no new or changed file under $HOPE_HOME or beside it. The requests the table's
bodies are made from are valid apart from the one bad value, so a check that goes missing shows
as a 2xx (or a 5xx), not as a pass.

Then what the table cannot show by itself: a model_config too big for the memory budget and a
budget above the deployment's are refused at the API and at the CLI (enqueue / sequential)
before a run exists, while a model that fits is accepted; and `~user` paths give the same answer
whether the user exists or not.
"""
from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import pytest

from test_api import App, settings  # noqa: F401 - the fixture test_api.py's tests use

OBS = [0.1, -0.2, 0.3, 0.0, 0.5, -0.4]
DEEP = 960  # nested this deep, a value once reached code that recursed (RecursionError, a 500)
MAX_MESSAGE = 2000  # an error says what is wrong; it does not echo a 1 MB body back


# -- what is sent ---------------------------------------------------------------------------------

class Raw(bytes):
    """A body sent as these bytes (for what json.dumps cannot write: NaN, 1e999, lone surrogates)."""


def raw_field(base: dict, field: str, literal: str) -> Raw:
    """`base` with `field` set to a JSON literal, as bytes."""
    body = dict(base)
    body[field] = "@@LITERAL@@"
    return Raw(json.dumps(body).replace('"@@LITERAL@@"', literal).encode())


def nested_text(depth: int) -> str:
    return '{"a": ' * depth + "1" + "}" * depth


def dumps(body) -> bytes:
    return bytes(body) if isinstance(body, Raw) else json.dumps(body).encode()


# -- bad values per kind of field -----------------------------------------------------------------

# (value, or a JSON literal string marked with LIT) -> the field's name must be in the message,
# except for literals JSON itself refuses (then "JSON" must be)
LIT = "literal:"
COMMON = [True, [], {}, [1], {"a": 1}, [0] * 100_000, LIT + nested_text(DEEP), LIT + "NaN", LIT + "Infinity",
          LIT + "-Infinity"]
INT = COMMON + ["2000", "x", "", 1.5, -10**9, 10**30, LIT + "1e999", LIT + "9" * 400, "\x00"]
FLOAT = COMMON + ["0.5", "x", -1.0, LIT + "1e999", LIT + "-1e999", LIT + "1" + "0" * 400]
TEXT = COMMON + [1, 2.5, "", "   ", "x" * 5000, LIT + '"\\ud800"']  # wrong for any text field
STR = TEXT + ["no-such-thing", "\x00"]  # and for a name that must be one of a few
BOOL = [[], {}, [1], {"a": 1}, LIT + nested_text(DEEP), LIT + "NaN", 1, 0, "true", "yes", ""]
PATH = [1, 2.5, True, [], {}, [""], "", "   ", "\x00", "ds\x00", "ds/\x00/x", "~nosuchuser/x", "~root/x", "~",
        "~/x", "a" * 256, "ds/" + "b" * 300, "x/" * 2100, "../../../../etc", "/etc", "/etc/passwd",
        "ds/../../../../../etc", "../outside/ds", "../../outside/ds", "no-such-dataset", "loop/x",
        LIT + '"\\ud800/x"', LIT + nested_text(DEEP)]
NOT_A_DATASET = ["notds.txt", "empty", "../token", "../hope.db"]  # exist inside the roots, hold no episodes
MODEL_CONFIG = [[1], "x", 1, True, LIT + "NaN", LIT + nested_text(DEEP), {"nope": 1},
                LIT + '{"window": ' + nested_text(DEEP) + "}",
                {"d_model": "64"}, {"d_model": 1.5}, {"d_model": True}, {"d_model": 0}, {"d_model": -3},
                {"d_model": 10**12}, {"d_model": 4096}, {"d_state": 2**31 - 1}, {"mlp_ratio": 10**6},
                {"min_timescale": -1.0}, {"min_timescale": 9.0, "max_timescale": 1.0}, {"obs_dim": 999},
                {"window": 1}, {"window": []}, {"window": {"k": "5"}}, {"window": {"k": 10**9}},
                {"window": {"nope": 1}}, {"window": {"horizons_s": 1}}, {"window": {"horizons_s": [[1]]}},
                {"window": {"horizons_s": [0.5]}}, {"window": {"duration_s": {"a": 1}}}, {"input": "frame"},
                {"d_model": [64]}, {"window": {"scale": "mid"}}, {"n_codes": 1}]
COMPONENTS = ["", ",", "vqvae,,fast_loop", "vqvae,", ",vqvae", "wings", "vqvae,wings", "fast_loop,vqvae",
              "vqvae,vqvae", "mid_loop", "x" * 300, [], [""], ["vqvae", 1], ["vqvae"] * 9, 3, True, {},
              LIT + nested_text(DEEP), "vqvae\x00"]
UNKNOWN_KEYS = [{"nope": 1}, {"run_dir": "/tmp/x"}, {"": 1}, {"\x00": 1}, {"k" * 5000: 1},
                {f"k{i}": i for i in range(200)}]


def run_fields() -> dict[str, list]:
    """The fields of a run request (POST /api/runs and the shared ones of /api/training/sequential)."""
    return {
        "data": PATH + NOT_A_DATASET,
        "steps": INT + [0, 10**9],
        "queue": TEXT + ["\x00", "GPU!", "a b", "q/../x", "q" * 65],
        "priority": INT + [1001],
        "max_attempts": INT + [0, 101],
        "vqvae_dir": PATH + NOT_A_DATASET + ["ds"],  # ds exists but is no checkpoint
        "vqvae_run": STR + ["r-nope", "r" * 65],
        "seed": INT + [2**32],
        "batch_size": INT + [0, 65537],
        "lr": FLOAT + [0],
        "warmup": INT + [10**9],
        "threads": INT + [0, 257],
        "checkpoint_every_steps": INT + [0],
        "checkpoint_every_s": FLOAT + [0],
        "keep_last": INT + [0, 1001],
        "log_every": INT + [0],
        "memory_budget_mb": FLOAT + [0, 1e12, 3073],
        "imagined_ratio": FLOAT + [1.0, 2.0],
        "model_config": MODEL_CONFIG,
    }


def endpoints(run_id: str) -> dict[str, tuple[dict, dict[str, list]]]:
    """path -> (a body valid but for the field under test, {field: bad values})."""
    runs_fields = {"component": STR, **run_fields()}
    seq_fields = {"components": COMPONENTS, **run_fields()}
    return {
        "/api/runs": ({"component": "fast_loop", "data": "ds", "steps": 10}, runs_fields),
        "/api/training/sequential": ({"components": "vqvae,fast_loop", "data": "ds", "steps": 10}, seq_fields),
        "/api/brain/infer": ({"component": "fast_loop", "observation": OBS},
                             # which names exist is BrainService's to say (404), once the body is valid
                             {"component": TEXT, "session": TEXT + ["s" * 200],
                              "reset": BOOL, "observation": [[], "0.1", {}, [True] * 6, [[0.1]] * 6, [None] * 6,
                                                             [0.0] * 5000, [0.0] * 100_000, ["x"] * 6,
                                                             LIT + "[NaN, 0, 0, 0, 0, 0]",
                                                             LIT + "[Infinity, 0, 0, 0, 0, 0]",
                                                             LIT + "[1e999, 0, 0, 0, 0, 0]",
                                                             LIT + "[0, -1e400, 0, 0, 0, 0]",
                                                             LIT + nested_text(DEEP)]}),
        # a run that does not exist: a value that slipped through would be a 404, not a gate child
        "/api/brain/promote": ({"run_id": "r-none"},
                               {"run_id": TEXT, "component": STR, "force": BOOL}),
        "/api/brain/promote#checkpoint": ({"checkpoint": "runs"}, {"checkpoint": PATH + ["token", "hope.db"]}),
        "/api/brain/rollback": ({"component": "fast_loop"}, {"component": STR}),
        "/api/sim/reflex": ({}, {"episodes": INT + [0, 6], "seed": INT + [2**31], "task": STR + ["fly"]}),
        f"/api/runs/{run_id}/cancel": ({}, {}),
        f"/api/runs/{run_id}/pause": ({}, {}),
        f"/api/runs/{run_id}/resume": ({}, {}),
    }


def field_cases(run_id: str):
    """(path, body, needle): every bad value of every field of every POST endpoint, and unknown keys."""
    for key, (base, fields) in endpoints(run_id).items():
        path = key.split("#")[0]
        for field, values in fields.items():
            for value in values:
                if isinstance(value, str) and value.startswith(LIT):
                    literal = value[len(LIT):]
                    json_refuses = literal.lstrip("[-").startswith(("NaN", "Infinity"))
                    yield path, raw_field(base, field, literal), "JSON" if json_refuses else field
                else:
                    yield path, {**base, field: value}, field
        for extra in UNKNOWN_KEYS:
            yield path, {**base, **extra}, "unknown field"


BODIES = [  # (body bytes, content type, needle) for every POST endpoint
    (b'{"component": "fast_loop",', "application/json", "not valid JSON"),
    (b"{'component': 'fast_loop'}", "application/json", "not valid JSON"),
    (b'{"a": 1} {"b": 2}', "application/json", "not valid JSON"),
    (b"\xff\xfe{}", "application/json", "UTF-8"),
    (b"[" * 100_000, "application/json", "JSON"),
    (nested_text(DEEP).encode(), "application/json", "nested"),
    (b'{"x": NaN}', "application/json", "NaN"),
    (b'{"x": Infinity}', "application/json", "Infinity"),
    (b"[]", "application/json", "JSON object"),
    (b"[1, 2, 3]", "application/json", "JSON object"),
    (b'"text"', "application/json", "JSON object"),
    (b"null", "application/json", "JSON object"),
    (b"42", "application/json", "JSON object"),
    (b"true", "application/json", "JSON object"),
    (b'{"component": "fast_loop"}', None, "application/json"),
    (b'{"component": "fast_loop"}', "text/plain", "application/json"),
    (b"component=fast_loop", "application/x-www-form-urlencoded", "application/json"),
    (b'--b\r\nContent-Disposition: form-data; name="a"\r\n\r\n1\r\n--b--\r\n', "multipart/form-data; boundary=b",
     "application/json"),
    (b"{}", "application/xml", "application/json"),
]
EMPTY_BODIES = [(b"", "application/json", "empty"), (b"   \n", "application/json", "empty")]

QUERY_CASES = [  # (path template, query, needle)
    ("/api/runs", "limit=abc", "limit"), ("/api/runs", "limit=0", "limit"), ("/api/runs", "limit=1_0", "limit"),
    ("/api/runs", "limit=%205", "limit"), ("/api/runs", "limit=%2B5", "limit"), ("/api/runs", "limit=1e3", "limit"),
    ("/api/runs", "limit=" + "9" * 30, "limit"), ("/api/runs", "limit=%D9%A5", "limit"),
    ("/api/runs", "limit=%00", "limit"), ("/api/runs", "state=sleeping", "state"),
    ("/api/runs", "state=queued,%00", "state"), ("/api/runs", "limitt=5", "unknown query parameter"),
    ("/api/runs", "x=1&y=2", "unknown query parameter"), ("/api/runs/{run}", "verbose=1", "unknown query parameter"),
    ("/api/runs/{run}/metrics", "after=abc", "after"), ("/api/runs/{run}/metrics", "after=-3", "after"),
    ("/api/runs/{run}/metrics", "after=1.5", "after"), ("/api/runs/{run}/metrics", "after=1_000", "after"),
    ("/api/runs/{run}/metrics", "after=%201", "after"), ("/api/runs/{run}/metrics", "after=" + "9" * 5000, "after"),
    ("/api/runs/{run}/metrics", "after=%00", "after"), ("/api/runs/{run}/metrics", "limit=0", "limit"),
    ("/api/runs/{run}/metrics", "limit=5001", "limit"), ("/api/runs/{run}/metrics", "limit=NaN", "limit"),
    ("/api/runs/{run}/metrics", "limit=Infinity", "limit"), ("/api/runs/{run}/metrics", "events=2", "events"),
    ("/api/runs/{run}/metrics", "events=yes", "events"), ("/api/runs/{run}/metrics", "events=%00", "events"),
    ("/api/runs/{run}/metrics", "event=1", "unknown query parameter"),
    ("/api/runs/{run}/metrics", "after=1&aftr=2", "unknown query parameter"),
    ("/api/brain", "history=lots", "history"), ("/api/brain", "history=1_0", "history"),
    ("/api/brain", "history=-1", "history"), ("/api/brain", "history=101", "history"),
    ("/api/brain", "history=%D9%A5", "history"),
]


# -- the app, its state, and "nothing was written" ------------------------------------------------

@pytest.fixture
def api(settings):  # noqa: F811 - test_api's settings fixture
    from registry import runs
    from hope_models.data.synthetic import generate_dataset

    home = Path(settings.home)
    a = App(settings, brain=False)
    datasets = Path(settings.datasets_dir)
    generate_dataset(datasets / "ds", 200, obs_dim=6, act_dim=2, seed=0, episode_seconds=(4.0, 6.0))
    (datasets / "empty").mkdir()
    (datasets / "notds.txt").write_text("not an episode\n")
    (datasets / "loop").symlink_to("loop")  # resolving loop/x loops
    outside = home.parent / "outside"
    generate_dataset(outside / "ds", 100, obs_dim=6, act_dim=2, seed=1, episode_seconds=(4.0, 6.0))
    with a.registry.session() as s:
        a.queued = runs.create_run(s, component="fast_loop", config={"data": str(datasets / "ds")}, total_steps=10,
                                   run_dir=str(Path(settings.runs_dir) / "r-queued")).id
    yield a
    a.close()


def written(api) -> tuple:
    """What a refused request must not change: the rows, and every file under $HOPE_HOME's parent
    ($HOPE_HOME and `outside`), but the registry's own database files."""
    from sqlalchemy import func, select

    from registry.models import Model, Run, RunEvent

    with api.registry.session(readonly=True) as s:
        rows = tuple(s.scalar(select(func.count()).select_from(t)) for t in (Run, RunEvent, Model))
        states = tuple(s.execute(select(Run.id, Run.state, Run.desired_state)).all())
    files = []
    for root, dirs, names in os.walk(Path(api.settings.home).parent):
        for name in dirs + names:
            p = Path(root) / name
            if not name.startswith("hope.db"):
                st = p.lstat()
                files.append((str(p), st.st_size, st.st_mtime_ns))
    return rows, states, tuple(sorted(files))


def send(api, path: str, body, ctype: str | None = "application/json"):
    headers = dict(api.headers)
    data = None
    if body is not None:
        data = body if isinstance(body, bytes) else dumps(body)
    if ctype is not None and data is not None:
        headers["Content-Type"] = ctype
    return api.client.post(path, data=data, headers=headers)


def check(api, failures: list, what: str, response, needle: str | None, before: list) -> None:
    """`before` holds what written() said before the request; it is brought up to date after a
    failure, so that one case that wrote is not blamed on all the cases after it."""
    obj = response.get_json(silent=True)
    error = obj.get("error") if isinstance(obj, dict) else None
    ok = 400 <= response.status_code < 500 and isinstance(error, str) and 0 < len(error.strip()) <= MAX_MESSAGE
    if ok and needle is not None:
        ok = needle in error
    now = written(api)
    if not ok:
        failures.append(f"{what}: got {response.status_code} {response.get_data(as_text=True)[:300]}")
    elif now != before[0]:
        changed = sorted(set(now[2]) ^ set(before[0][2]))[:3] or [now[:2], before[0][:2]]
        failures.append(f"{what}: refused ({response.status_code}) but something was written: {changed}")
    before[0] = now


def short(value) -> str:
    text = repr(value)
    return text if len(text) <= 100 else text[:97] + "..."


# -- the table ------------------------------------------------------------------------------------

def test_every_field_of_every_post_endpoint(api):
    before = [written(api)]
    failures: list[str] = []
    n = 0
    for path, body, needle in field_cases(api.queued):
        check(api, failures, f"POST {path} {short(body)}", send(api, path, body), needle, before)
        n += 1
    assert n > 700
    assert not failures, f"{len(failures)} of {n} cases:\n" + "\n".join(failures)


def test_every_post_endpoint_refuses_bodies_that_are_not_a_json_object(api):
    before = [written(api)]
    failures: list[str] = []
    for path in [p.split("#")[0] for p in endpoints(api.queued)]:
        takes_no_input = path.endswith(("/cancel", "/pause", "/resume"))
        for data, ctype, needle in BODIES + ([] if takes_no_input else EMPTY_BODIES):
            check(api, failures, f"POST {path} {ctype} {data[:60]!r}", send(api, path, data, ctype), needle, before)
        if takes_no_input:  # no fields at all: {} and an empty body are its only inputs
            for body in ({"force": True}, {"run_id": api.queued}, {"": None}):
                check(api, failures, f"POST {path} {body}", send(api, path, body), "unknown field", before)
    assert not failures, "\n".join(failures)


def test_query_parameters_of_the_gets(api):
    before = [written(api)]
    failures: list[str] = []
    for template, query, needle in QUERY_CASES:
        url = template.format(run=api.queued) + "?" + query
        check(api, failures, f"GET {url[:100]}", api.client.get(url, headers=api.headers), needle, before)
    assert not failures, "\n".join(failures)


# -- what the table cannot show by itself ---------------------------------------------------------

def test_user_homes_are_not_looked_up_so_no_answer_tells_which_users_exist(api):
    answers = set()
    for field, path in (("data", "/api/runs"), ("vqvae_dir", "/api/runs"), ("checkpoint", "/api/brain/promote")):
        for name in ("root", "nosuchuser-8f3a", "nobody", ""):
            body = {"component": "fast_loop", "data": "ds"} if path == "/api/runs" else {}
            r = send(api, path, {**body, field: f"~{name}/x"})
            assert r.status_code == 400, r.get_data(as_text=True)
            answers.add((field, r.get_json()["error"]))
    assert len(answers) == 3, answers  # one answer per field, whoever the user


def test_a_model_too_big_for_the_budget_is_refused_before_a_run_exists(api):
    before = written(api)
    base = {"component": "fast_loop", "data": "ds", "steps": 10}
    big = send(api, "/api/runs", {**base, "model_config": {"d_model": 4096}})
    assert big.status_code == 400, big.get_data(as_text=True)
    assert "estimated" in big.get_json()["error"] and "exceeds the budget of 3072 MB" in big.get_json()["error"]
    batch = send(api, "/api/runs", {**base, "batch_size": 65536, "model_config": {"d_model": 512}})
    assert batch.status_code == 400 and "batch" in batch.get_json()["error"], batch.get_data(as_text=True)
    # the deployment's budget bounds what a request may ask for; it can still make itself smaller
    more = send(api, "/api/runs", {**base, "memory_budget_mb": 1e12})
    assert more.status_code == 400 and "3072" in more.get_json()["error"], more.get_data(as_text=True)
    less = send(api, "/api/runs", {**base, "memory_budget_mb": 200})
    assert less.status_code == 400 and "exceeds the budget of 200 MB" in less.get_json()["error"]
    chain = send(api, "/api/training/sequential", {"components": "vqvae,fast_loop", "data": "ds",
                                                   "model_config": {"d_model": 64}})
    assert chain.status_code == 400 and "model_config for vqvae" in chain.get_json()["error"]
    assert written(api) == before
    fits = send(api, "/api/runs", {**base, "model_config": {"d_model": 64}, "memory_budget_mb": 2048})
    assert fits.status_code == 201, fits.get_data(as_text=True)
    assert fits.get_json()["run"]["config"]["model_config"] == {"d_model": 64}


def _cli(monkeypatch, settings, module, argv: list[str]) -> int:
    monkeypatch.setenv("HOPE_HOME", str(settings.home))
    parser = argparse.ArgumentParser()
    module.add_arguments(parser)
    return module.run(parser.parse_args(argv))


def test_the_cli_refuses_what_the_api_refuses_before_a_run_exists(api, settings, monkeypatch, capsys):  # noqa: F811
    from daemon.cli import enqueue, sequential

    before = written(api)
    ds = str(Path(settings.datasets_dir) / "ds")
    cases = [
        (enqueue, ["--component", "fast_loop", "--data", str(Path(settings.datasets_dir) / "notds.txt")],
         "not a dataset"),
        (enqueue, ["--component", "fast_loop", "--data", str(Path(settings.datasets_dir) / "empty")],
         "no episode files"),
        (enqueue, ["--component", "fast_loop", "--data", ds, "--model-config", '{"d_modle": 64}'], "d_modle"),
        (enqueue, ["--component", "fast_loop", "--data", ds, "--model-config", '{"d_model": 4096}'],
         "exceeds the budget"),
        (enqueue, ["--component", "fast_loop", "--data", ds, "--memory-budget-mb", "1e12"], "memory_budget_mb"),
        (enqueue, ["--component", "fast_loop", "--data", "~nosuchuser-8f3a/x"], "data"),
        (sequential, ["--components", "vqvae,,fast_loop", "--data", ds], "empty component name"),
        (sequential, ["--components", "vqvae,fast_loop", "--data", ds, "--model-config", '{"d_model": 64}'],
         "model_config for vqvae"),
    ]
    for module, argv, needle in cases:
        assert _cli(monkeypatch, settings, module, argv) == 2, argv
        err = capsys.readouterr().err
        assert needle in err, (argv, err)
    assert written(api) == before
    assert _cli(monkeypatch, settings, enqueue, ["--component", "fast_loop", "--data", ds, "--model-config",
                                                 '{"d_model": 64}', "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["state"] == "queued"


NO_TORCH = """
import json, sys
from pathlib import Path
from registry.db import Registry
from hope_models.data.synthetic import generate_dataset
from hope_models.settings import load_settings
from webapp import create_app
settings = load_settings(env={"HOPE_HOME": sys.argv[1], "HOPE_THERMAL_ZONE": "", "HOPE_VCGENCMD": ""})
generate_dataset(Path(settings.datasets_dir) / "ds", 200, obs_dim=6, act_dim=2, seed=0, episode_seconds=(4.0, 6.0))
token = "t" * 40
app, _ = create_app(settings, token=token, registry=Registry.open(settings))
h = {"Authorization": "Bearer " + token}
out = [app.test_client().post("/api/runs", headers=h, json={"component": "fast_loop", "data": "ds",
                                                            "model_config": {"d_model": d}})
       for d in (4096, 64)]
print(json.dumps({"status": [r.status_code for r in out], "error": out[0].get_json().get("error"),
                  "torch": "torch" in sys.modules}))
"""


def test_the_webapp_estimates_a_request_from_its_config_without_torch(tmp_path):
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-c", NO_TORCH, str(tmp_path / "home")], capture_output=True, text=True,
                          cwd=Path(__file__).resolve().parents[1], timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["status"] == [400, 201] and "estimated" in out["error"], out
    assert out["torch"] is False  # the webapp never imports torch (the model is never built here)
