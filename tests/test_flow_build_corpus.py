"""The build-corpus flow, for real: a loopback Prefect server, the deployments in infra/prefect.yaml,
a process worker and a local Dask cluster; then the flow called in-process on ephemeral Prefect."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tarfile
import time
from pathlib import Path

import httpx
import pytest

REPO = Path(__file__).resolve().parents[1]
PREFECT = str(Path(sys.executable).with_name("prefect"))
POOL = "marionette-local"
DEPLOYMENT = "build-corpus/local"
SYNTH = {"recordings": 3, "seconds": 6.0, "seed": 11, "width": 160, "height": 96}
SMALL_VIDEO = {"video_height": 64, "video_width": 112, "chunk_frames": 17}

pytestmark = pytest.mark.quality  # a real Prefect server, worker and Dask cluster


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def prefect_env(home: Path, api_url: str | None) -> dict[str, str]:
    """An environment isolated in ``home``: own database, no telemetry, no UI, quick worker polling, and the server's
    services that no test here uses off (the scheduler, with every schedule declared off; late runs, pause expirations,
    cancellation clean-up, the foreman's worker health, automations' triggers): idle, they cost the server 9 CPU-seconds
    a minute on two cores, 3 without them."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    env.update(
        PREFECT_HOME=str(home),
        PREFECT_API_DATABASE_CONNECTION_URL=f"sqlite+aiosqlite:///{home / 'prefect.db'}",
        PREFECT_SERVER_ANALYTICS_ENABLED="false",
        PREFECT_UI_ENABLED="false",
        PREFECT_SERVER_UI_ENABLED="false",
        DO_NOT_TRACK="1",
        PREFECT_WORKER_QUERY_SECONDS="1",
        PREFECT_CLI_WRAP_LINES="false",
    )
    for service in ("SCHEDULER", "LATE_RUNS", "PAUSE_EXPIRATIONS", "CANCELLATION_CLEANUP", "FOREMAN", "TRIGGERS"):
        env[f"PREFECT_SERVER_SERVICES_{service}_ENABLED"] = "false"
    if api_url:
        env["PREFECT_API_URL"] = api_url
    return env


def cli(env: dict, *args: str, timeout: float = 120) -> str:
    p = subprocess.run([PREFECT, *args], env=env, cwd=REPO, capture_output=True, text=True, timeout=timeout)
    assert p.returncode == 0, f"prefect {' '.join(args)} failed ({p.returncode}):\n{p.stdout}\n{p.stderr}"
    return p.stdout


def start(cmd: list[str], env: dict, log: Path) -> subprocess.Popen:
    """A background process in its own session, so teardown can stop it and all its children."""
    fh = open(log, "wb")  # noqa: SIM115 — closed with the process in stop()
    return subprocess.Popen(cmd, env=env, cwd=REPO, stdout=fh, stderr=subprocess.STDOUT, start_new_session=True)


def stop(proc: subprocess.Popen) -> None:
    for sig, wait in ((signal.SIGINT, 5), (signal.SIGTERM, 10), (signal.SIGKILL, 10)):  # a worker exits on SIGINT
        if proc.poll() is not None:
            break
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            break
        try:
            proc.wait(timeout=wait)
        except subprocess.TimeoutExpired:
            continue
    if proc.stdout:
        proc.stdout.close()


def tail(log: Path, n: int = 4000) -> str:
    return log.read_text(errors="replace")[-n:] if log.exists() else ""


@pytest.fixture(scope="module")
def synth_small(tmp_path_factory) -> Path:
    from marionette.synth import generate

    root = tmp_path_factory.mktemp("synth-flow")
    generate(root, **SYNTH)
    return root


@pytest.fixture(scope="module")
def local_prefect(tmp_path_factory):
    """Server on 127.0.0.1, a process work pool, the deployments from infra/prefect.yaml, a worker."""
    home = tmp_path_factory.mktemp("prefect-home")
    port = free_port()
    api = f"http://127.0.0.1:{port}/api"
    env = prefect_env(home, api)
    procs: list[subprocess.Popen] = []
    logs = {"server": home / "server.log", "worker": home / "worker.log"}
    try:
        procs.append(
            start([PREFECT, "server", "start", "--host", "127.0.0.1", "--port", str(port), "--no-ui"], env, logs["server"])
        )
        deadline = time.monotonic() + 120
        while True:
            try:
                if httpx.get(f"{api}/health", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            assert procs[0].poll() is None, f"server exited:\n{tail(logs['server'])}"
            assert time.monotonic() < deadline, f"server not healthy after 120 s:\n{tail(logs['server'])}"
            time.sleep(0.5)
        cli(env, "work-pool", "create", POOL, "--type", "process")
        cli(env, "deploy", "--no-prompt", "--prefect-file", "infra/prefect.yaml", "--all")
        procs.append(start([PREFECT, "worker", "start", "--pool", POOL, "--type", "process"], env, logs["worker"]))
        yield {"env": env, "api": api, "logs": logs}
    finally:
        for p in reversed(procs):
            stop(p)


def cli_value(v) -> object:
    """A parameter as ``prefect deployment run -p key=value`` reads it: its text as JSON where it parses, else the text."""
    try:
        return json.loads(str(v))
    except ValueError:
        return str(v)


RETRY_CODES = (408, 429, 502, 503)  # what Prefect's own client retries: a busy server (its SQLite locked) says 503


def rest(method: str, url: str, **kwargs) -> httpx.Response:
    """A call to the server's REST API, retried as Prefect's client retries it (those codes, backing off to 8 s)."""
    for attempt in range(8):
        r = httpx.request(method, url, timeout=10, **kwargs)
        if r.status_code not in RETRY_CODES:
            return r
        time.sleep(min(8.0, 0.25 * 2**attempt))
    return r


def run_deployment(prefect: dict, timeout: float = 240, deployment: str = DEPLOYMENT, command: bool = False, **params) -> str:
    """A run of ``deployment`` with ``params``, made by ``prefect deployment run`` with ``-p`` parameters (``command``), else
    by the server's API as that command makes it (the parameters read as the command reads them, the run scheduled
    now); waits for a terminal state; returns the run id. Either way the worker runs it."""
    if command:
        args = ["deployment", "run", deployment]
        for k, v in params.items():
            args += ["-p", f"{k}={v}"]
        out = cli(prefect["env"], *args)
        m = re.search(r"UUID:\s*([0-9a-f-]{36})", out)
        assert m, out
        run_id = m.group(1)
    else:
        dep = rest("GET", f"{prefect['api']}/deployments/name/{deployment}")
        assert dep.status_code == 200, f"{deployment}: {dep.text}"
        body = {"parameters": {k: cli_value(v) for k, v in params.items()}}
        made = rest("POST", f"{prefect['api']}/deployments/{dep.json()['id']}/create_flow_run", json=body)
        assert made.status_code == 201, f"{deployment}: {made.text}"
        run_id = made.json()["id"]
    deadline = time.monotonic() + timeout
    while True:
        state = rest("GET", f"{prefect['api']}/flow_runs/{run_id}").json()["state"]
        if state["type"] in ("COMPLETED", "FAILED", "CRASHED", "CANCELLED"):
            break
        assert time.monotonic() < deadline, f"flow run {run_id} still {state['type']}:\n{tail(prefect['logs']['worker'])}"
        time.sleep(1)
    assert state["type"] == "COMPLETED", f"flow run {run_id}: {state}\n{tail(prefect['logs']['worker'], 8000)}"
    return run_id


def shard_files(corpus: Path) -> dict[str, tuple[bytes, int]]:
    return {str(p.relative_to(corpus)): (p.read_bytes(), p.stat().st_mtime_ns) for p in sorted(corpus.glob("*/shard-*"))}


def shard_files_bytes(corpus: Path) -> dict[str, bytes]:
    return {k: v[0] for k, v in shard_files(corpus).items()}


def stage_bytes(corpus: Path) -> dict[str, bytes]:
    """Every file of every stage (manifest, contributions, chunks) by its path under ``terrain/``."""
    root = corpus / "terrain"
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def terrain_files(corpus: Path) -> dict[str, tuple[int, bytes]]:
    return {p.name: (p.stat().st_mtime_ns, p.read_bytes()) for p in sorted((corpus / "terrain").rglob("*.trn2"))}


@pytest.fixture(scope="module")
def dask_build(local_prefect, synth_small, tmp_path_factory) -> tuple[Path, Path, str]:
    """(source, corpus, flow run id) of the build-corpus deployment run once, by the command a user types, over the
    small source and a fourth recording without its rgb.mp4, which the build quarantines."""
    root = tmp_path_factory.mktemp("dask-build")
    source = root / "source"
    shutil.copytree(synth_small, source)
    bad = source / "data_part1" / "rec0003"
    shutil.copytree(source / "data_part1" / "rec0002", bad)
    (bad / "rgb.mp4").unlink()
    corpus = root / "corpus"
    return source, corpus, run_deployment(local_prefect, command=True, source=source, corpus=corpus, **SMALL_VIDEO)


@pytest.mark.timeout(600)
def test_deployment_builds_on_two_dask_workers(dask_build):
    source, corpus, run_id = dask_build
    info = json.loads((corpus / "meta" / "info.json").read_text())
    assert info["total_ingested"] == 3 and info["total_quarantined"] == 1
    report = json.loads((corpus / "meta" / "builds" / f"{run_id}.json").read_text())
    assert report["flow_run_id"] == run_id
    assert [s["status"] for s in report["samples"]] == ["ingested"] * 3 + ["quarantined"]
    assert "rgb.mp4" in report["samples"][3]["reason"]
    assert report["corpus_totals"]["total_ingested"] == 3 and report["corpus_totals"]["total_quarantined"] == 1
    addresses = {s["worker"].split("/pid-")[0] for s in report["samples"]}
    assert len(addresses) >= 2 and all(a.startswith("tcp://127.0.0.1:") for a in addresses), addresses
    shards = shard_files(corpus)
    assert len(shards) == 9  # a state, a video and a pose shard per ingested sample
    # the stage's terrain was scanned after finalize
    assert sorted(report["terrain"]["default"]["scanned"][i]["sample"] for i in range(3)) == [
        s["sample"] for s in report["samples"][:3]
    ]
    chunks = terrain_files(corpus)
    assert chunks
    # each recording was scanned by a task on a Dask worker
    scanned_on = {s["worker"].split("/pid-")[0] for s in report["terrain"]["default"]["scanned"]}
    assert all(a.startswith("tcp://127.0.0.1:") for a in scanned_on), scanned_on
    # then every video chunk's pose-control target was rendered into the video shards
    pose = report["terrain"]["_pose_targets"]
    assert pose["chunks"] > 0 and len(pose["rendered"]) == pose["chunks"]
    assert pose["workers"] and all(w.startswith("tcp://127.0.0.1:") for w in pose["workers"]), pose["workers"]  # on Dask
    for tar_path in sorted((corpus / "video").glob("*.tar")):
        with tarfile.open(tar_path) as tar, tarfile.open(corpus / "pose" / tar_path.name) as pose:
            names, posed = tar.getnames(), pose.getnames()
        assert [n.replace(".pose.gbz", "") for n in posed if n.endswith(".pose.gbz")] == [
            n.replace(".rgb.mp4", "") for n in names if n.endswith(".rgb.mp4")
        ]


def test_the_dask_build_equals_a_serial_build_byte_for_byte(dask_build, tmp_path):
    """The whole build, ingest, scan and render fanned out on Dask, equals a serial build in one process."""
    from marionette.ingest import IngestOptions, VideoSettings
    from marionette.pipeline import build

    source, corpus, _ = dask_build
    serial = tmp_path / "serial"
    small = VideoSettings(
        height=SMALL_VIDEO["video_height"], width=SMALL_VIDEO["video_width"], chunk_frames=SMALL_VIDEO["chunk_frames"]
    )
    done = build(source, serial, IngestOptions(video=small), workers=1, progress=False)
    assert done["refresh"].pose["workers"] == [f"{socket.gethostname()}/pid-{os.getpid()}"]  # the one-process pass
    assert stage_bytes(serial) == stage_bytes(corpus) and shard_files_bytes(serial) == shard_files_bytes(corpus)


def test_a_second_deployment_run_does_no_work(local_prefect, dask_build):
    """The same build again, on one Dask worker (the cluster's size is not the corpus's): every sample unchanged."""
    source, corpus, _ = dask_build
    shards, chunks = shard_files(corpus), terrain_files(corpus)
    run_id2 = run_deployment(local_prefect, source=source, corpus=corpus, n_workers=1, **SMALL_VIDEO)
    report2 = json.loads((corpus / "meta" / "builds" / f"{run_id2}.json").read_text())
    assert [s["status"] for s in report2["samples"]] == ["unchanged"] * 4, report2["samples"]
    assert report2["counts"] == {"unchanged": 4}
    assert shard_files(corpus) == shards  # same bytes, same mtimes
    assert json.loads((corpus / "meta" / "info.json").read_text())["total_ingested"] == 3
    assert len(report2["terrain"]["default"]["unchanged"]) == 3 and report2["terrain"]["default"]["chunks_written"] == []
    assert report2["terrain"]["_pose_targets"]["rendered"] == [] and report2["terrain"]["_pose_targets"]["shards_rewritten"] == []
    assert terrain_files(corpus) == chunks
    artifacts = rest(
        "POST", f"{local_prefect['api']}/artifacts/filter", json={"artifacts": {"key": {"any_": ["build-corpus-report"]}}}
    )
    assert any(a["flow_run_id"] == run_id2 and "unchanged" in a["data"] for a in artifacts.json())


def test_the_rescan_deployment_over_an_unchanged_corpus_rewrites_no_chunk(local_prefect, dask_build):
    """The rescan-stage/incremental deployment over the built corpus reads nothing and rewrites no chunk."""
    _, corpus, _ = dask_build
    chunks = terrain_files(corpus)
    run_deployment(local_prefect, deployment="rescan-stage/incremental", corpus=corpus, n_workers=1)
    assert terrain_files(corpus) == chunks


@pytest.mark.timeout(600)
def test_train_dynamics_deployment_trains_under_ddp_resumes_and_reports(local_prefect, corpus, tmp_path):
    """The train-dynamics/weekly deployment (schedule declared, off) run by the worker with nproc=2, each rank's
    batches stacked by a DataLoader worker process."""
    dep = rest("GET", f"{local_prefect['api']}/deployments/name/train-dynamics/weekly").json()
    assert [(s["schedule"]["cron"], s["active"]) for s in dep["schedules"]] == [("0 3 * * 0", False)]
    out = tmp_path / "dynamics"
    params = {"corpus": corpus, "out": out, "steps": 4, "batch_size": 4, "window": 16, "checkpoint_every": 2, "nproc": 2}
    params["loader_workers"] = 1
    run_id = run_deployment(local_prefect, deployment="train-dynamics/weekly", **params)
    from marionette.checkpoint import latest_checkpoint

    ckpt = latest_checkpoint(out)
    assert ckpt is not None and ckpt.name == "step-00000004"
    assert json.loads((ckpt / "meta.json").read_text())["train_config"]["loader_workers"] == 1
    assert (out / "tensorboard").is_dir() and any((out / "tensorboard").iterdir())
    artifacts = rest(
        "POST", f"{local_prefect['api']}/artifacts/filter", json={"artifacts": {"key": {"any_": ["train-dynamics-report"]}}}
    ).json()
    assert any(a["flow_run_id"] == run_id and "step-00000004" in a["data"] for a in artifacts)


@pytest.mark.timeout(600)
def test_train_observation_deployment_renders_targets_trains_and_reports(local_prefect, corpus, tmp_path):
    """The train-observation/weekly deployment (schedule declared, off) on a corpus without pose targets."""
    dep = rest("GET", f"{local_prefect['api']}/deployments/name/train-observation/weekly").json()
    assert [(s["schedule"]["cron"], s["active"]) for s in dep["schedules"]] == [("0 4 * * 0", False)]
    copy = tmp_path / "corpus"
    shutil.copytree(corpus, copy)
    out = tmp_path / "observation"
    params = {
        "corpus": copy,
        "out": out,
        "steps": 4,
        "batch_size": 2,
        "frames": 5,
        "reduce": 4,
        "patch": 2,
        "checkpoint_every": 2,
        "n_workers": 1,
    }
    run_id = run_deployment(local_prefect, deployment="train-observation/weekly", **params)
    from marionette.checkpoint import latest_checkpoint

    ckpt = latest_checkpoint(out)
    assert ckpt is not None and ckpt.name == "step-00000004"
    with tarfile.open(sorted((copy / "pose").glob("*.tar"))[0]) as tar:
        assert any(n.endswith(".pose.gbz") for n in tar.getnames())  # the flow rendered the targets first
    artifacts = rest(
        "POST", f"{local_prefect['api']}/artifacts/filter", json={"artifacts": {"key": {"any_": ["train-observation-report"]}}}
    ).json()
    assert any(a["flow_run_id"] == run_id and "step-00000004" in a["data"] for a in artifacts)


@pytest.mark.timeout(600)
def test_evaluate_deployment_writes_the_report_and_publishes_it(local_prefect, corpus, tmp_path):
    """The evaluate/weekly deployment (schedule declared, off) on a small checkpoint: report files and artifacts."""
    from marionette.dynamics.config import TrainConfig
    from marionette.dynamics.train import train

    dep = rest("GET", f"{local_prefect['api']}/deployments/name/evaluate/weekly").json()
    assert [(s["schedule"]["cron"], s["active"]) for s in dep["schedules"]] == [("0 6 * * 1", False)]
    runs = tmp_path / "dynamics"
    train(corpus, runs, TrainConfig(preset="tiny", steps=4, batch_size=4, window=16), log=lambda *_: None)
    out = tmp_path / "report"
    params = {
        "dynamics": runs,
        "corpus": corpus,
        "out": out,
        "observation": "null",
        "segments": 2,
        "seed_frames": 16,
        "horizon": 24,
    }
    run_id = run_deployment(local_prefect, deployment="evaluate/weekly", **params)
    report = json.loads((out / "report.json").read_text())
    assert (out / "report.md").read_text().startswith("# Evaluation")
    # the session corpus's 10 s recordings hold no 16 s rollout: Tables 1 and 3 say so, Table 2's plots are drawn
    assert "Not run" in (out / "report.md").read_text() and {"class_ratios", "compliance", "drift"} <= set(report["plots"])
    assert all((out / f).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for f in report["plots"].values())
    artifacts = rest(
        "POST",
        f"{local_prefect['api']}/artifacts/filter",
        json={"artifacts": {"key": {"any_": ["evaluation-report", "evaluation-headline"]}}},
    ).json()
    mine = {a["key"]: a for a in artifacts if a["flow_run_id"] == run_id}
    assert set(mine) == {"evaluation-report", "evaluation-headline"}
    assert "Controllability probe" in mine["evaluation-report"]["data"]
    assert len(report["windows"]) == 2 and report["windows"][0]["horizon"] == 24
