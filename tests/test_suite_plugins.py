"""The suite's own machinery (tests/fixtures/): the per-test budget fails a run and names the test, a fixture's
setup is shared among its readers, tiers follow markers and fixtures, and a shared build is made once and remade
after a crash."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from fixtures.shared import build_once, built

pytestmark = pytest.mark.unit

TESTS = Path(__file__).resolve().parent

# plugins installed beside pytest that these small runs never use (the suite's own addopts leave out the first two)
UNUSED_PLUGINS = ("-p", "no:dash", "-p", "no:anyio", "-p", "no:hypothesispytest")

INNER = """
import time
import pytest


@pytest.fixture(scope="module")
def shared_setup():
    time.sleep(0.9)

def test_a(shared_setup):
    pass

def test_b(shared_setup):
    pass

def test_c(shared_setup):
    pass

def test_sleeps():
    time.sleep(0.7)
"""


@pytest.fixture
def inner(pytester, monkeypatch) -> pytest.Pytester:
    monkeypatch.setenv("PYTHONPATH", str(TESTS))
    pytester.makepyfile(test_inner=INNER)
    return pytester


def test_a_test_over_the_budget_fails_the_run_and_is_named(inner):
    """Budget 0.5 s: the test that sleeps 0.7 s fails the run, named with its time; the three tests that share a
    0.9 s fixture are charged 0.3 s each and pass it, though the first of them set it up."""
    report = inner.path / "budget.json"
    r = inner.runpytest_subprocess(
        *UNUSED_PLUGINS, "-p", "fixtures.budget", "--test-budget", "0.5", "--budget-report", str(report)
    )
    assert r.ret == pytest.ExitCode.TESTS_FAILED
    r.stdout.fnmatch_lines(["*over 0.5 s: test_inner.py::test_sleeps took 0.7* s*", "*4 passed*"])
    assert "over 0.5 s: test_inner.py::test_a" not in r.stdout.str()
    costs = json.loads(report.read_text())["tests"]
    assert costs["test_inner.py::test_a"]["fixture_share"] == pytest.approx(0.3, abs=0.05)
    assert costs["test_inner.py::test_a"]["seconds"] < 0.5 and costs["test_inner.py::test_sleeps"]["seconds"] >= 0.7


def test_a_run_within_the_budget_passes_and_names_its_slowest_test(inner):
    r = inner.runpytest_subprocess(*UNUSED_PLUGINS, "-p", "fixtures.budget", "--test-budget", "2")
    assert r.ret == pytest.ExitCode.OK
    r.stdout.fnmatch_lines(["*test budget 2 s: the slowest test, test_inner.py::test_sleeps, took 0.7* s*"])


def test_a_fixture_read_by_one_test_is_charged_to_it_whole(pytester, monkeypatch):
    monkeypatch.setenv("PYTHONPATH", str(TESTS))
    pytester.makepyfile(
        test_solo=INNER.replace("def test_b(shared_setup):\n    pass\n", "").replace("def test_c(shared_setup):\n    pass\n", "")
    )
    r = pytester.runpytest_subprocess(*UNUSED_PLUGINS, "-p", "fixtures.budget", "--test-budget", "0.8", "-k", "test_a")
    assert r.ret == pytest.ExitCode.TESTS_FAILED
    r.stdout.fnmatch_lines(["*over 0.8 s: test_solo.py::test_a took 0.9* s*"])


def test_a_bad_budget_is_refused_where_it_is_parsed(inner):
    r = inner.runpytest_subprocess(*UNUSED_PLUGINS, "-p", "fixtures.budget", "--test-budget", "-1")
    assert r.ret == pytest.ExitCode.USAGE_ERROR
    r.stderr.fnmatch_lines(["*--test-budget*invalid*-1*"])


def test_tiers_follow_markers_and_the_fixtures_a_test_reads(pytester, monkeypatch):
    """A test reading a corpus fixture is in the corpus tier, one reading a trained model in the quality tier, a
    marked module's tests in at least its tier; ``-m unit`` selects the rest. Modules run in the order of their highest
    tier, their tests in file order."""
    monkeypatch.setenv("PYTHONPATH", str(TESTS))
    pytester.makeconftest('pytest_plugins = ["fixtures.tiers"]')
    pytester.makepyfile(
        test_plain="""
import pytest

@pytest.fixture
def corpus():
    return 1

@pytest.fixture
def tiny_dynamics():
    return 2

def test_arrays():
    pass

def test_reads_a_corpus(corpus):
    pass

def test_reads_a_model(tiny_dynamics):
    pass

@pytest.mark.quality
def test_marked(corpus):
    pass
""",
        test_marked="""
import pytest

pytestmark = pytest.mark.corpus

def test_in_a_corpus_module():
    pass
""",
    )

    def selected(tier: str) -> set[str]:
        r = pytester.runpytest_subprocess(*UNUSED_PLUGINS, "--co", "-q", "-m", tier)
        return {line.split("::")[1] for line in r.stdout.lines if "::" in line}

    assert selected("unit") == {"test_arrays"}
    assert selected("corpus") == {"test_reads_a_corpus", "test_in_a_corpus_module"}
    assert selected("quality") == {"test_reads_a_model", "test_marked"}
    order = [
        line.split("::")[1] for line in pytester.runpytest_subprocess(*UNUSED_PLUGINS, "--co", "-q").stdout.lines if "::" in line
    ]
    assert order == ["test_in_a_corpus_module", "test_arrays", "test_reads_a_corpus", "test_reads_a_model", "test_marked"]


def test_a_shared_build_is_made_once_and_remade_after_a_crash(tmp_path):
    calls = []

    def make(out: Path) -> dict:
        calls.append(out)
        (out / "data").write_text("x")
        return {"n": len(calls)}

    first = build_once(tmp_path, "thing", make)
    again = build_once(tmp_path, "thing", make)
    assert first[0] == again[0] == tmp_path / "thing" and first[1]["n"] == again[1]["n"] == 1 and len(calls) == 1
    assert built(tmp_path)["thing"]["n"] == 1

    def crash(out: Path) -> dict:
        (out / "half").write_text("x")
        raise RuntimeError("killed mid-build")

    with pytest.raises(RuntimeError):
        build_once(tmp_path, "other", crash)
    assert (tmp_path / "other" / "half").exists() and not (tmp_path / "other.json").exists()
    out, result = build_once(tmp_path, "other", make)
    assert result["n"] == 2 and not (out / "half").exists() and (out / "data").exists()
