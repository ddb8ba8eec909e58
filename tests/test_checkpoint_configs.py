"""A checkpoint's saved model config is checked on load: every size within its bounds, exact types, and the memory
the model would take within the machine's, refused by name before anything is allocated."""

from __future__ import annotations

import json
import time

import pytest

from marionette.checkpoint import CHECKPOINT_VERSION, read_config, read_meta
from marionette.dynamics.config import DynamicsConfig
from marionette.model_size import check_memory
from marionette.observation.config import OBS_PRESETS, ObservationConfig
from marionette.observation.train import load_model
from marionette.schema import load_scene


def _dynamics_json() -> dict:
    return DynamicsConfig.preset("tiny", load_scene("duel"), (12, 9)).to_json()


def _checkpoint(tmp_path, key: str, config: dict, kind: str):
    d = tmp_path / "step-00000001"
    d.mkdir(exist_ok=True)
    (d / "meta.json").write_text(json.dumps({"version": CHECKPOINT_VERSION, "kind": kind, key: config}))
    return d


@pytest.mark.parametrize(
    "edit, named",
    [
        (lambda c: c["pose_gpt"].update(width=30000), r"width 30000 is not an integer in \[1, 16384\]"),
        (lambda c: c["action_gpt"].update(layers=100000), r"layers 100000 is not an integer in \[1, 512\]"),
        (lambda c: c.update(window=1e9), r"window 1000000000.0 is not an integer in \[1, 65536\]"),
        (lambda c: c["action_gpt"].update(heads=0), r"heads 0 is not an integer"),
        (lambda c: c["pose_gpt"].update(layers="2"), r"layers '2' is not an integer"),
        (lambda c: c["pose_gpt"].update(layers=True), r"layers True is not an integer"),
        (lambda c: c.update(vocab_sizes=[12, -1]), r"vocab sizes \(12, -1\) must be ≥ 1"),
        (lambda c: c["pose_gpt"].update(depth=3), r"unknown fields \['depth'\]"),
        (lambda c: c.update(pose_gpt=[1, 2]), r"pose_gpt is not an object"),
        (
            lambda c: c["pose_gpt"].update(width=16384, layers=512, heads=256),
            r"parameters, [\d,.]+ GiB of float32 weights, more than this machine's",
        ),
    ],
)
def test_a_dynamics_checkpoint_config_out_of_bounds_is_refused_by_name(tmp_path, edit, named):
    config = _dynamics_json()
    edit(config)
    ckpt = _checkpoint(tmp_path, "dynamics_config", config, "dynamics")
    t0 = time.perf_counter()
    with pytest.raises(ValueError, match=named) as err:
        read_config(ckpt, read_meta(ckpt), "dynamics_config", DynamicsConfig)
    assert time.perf_counter() - t0 < 1.0
    assert str(ckpt / "meta.json") in str(err.value)


def test_the_saved_configs_that_train_still_load(tmp_path):
    config = _dynamics_json()
    ckpt = _checkpoint(tmp_path, "dynamics_config", config, "dynamics")
    assert read_config(ckpt, read_meta(ckpt), "dynamics_config", DynamicsConfig).to_json() == config
    paper = DynamicsConfig.preset("paper", load_scene("duel"), (12, 9))
    assert DynamicsConfig.from_json(paper.to_json()) == paper
    for preset in OBS_PRESETS.values():
        assert ObservationConfig.from_json(preset.to_json()) == preset


@pytest.mark.parametrize(
    "field, value, named",
    [
        ("width", 30000, r"width 30000 is not an integer"),
        ("layers", 100000, r"layers 100000 is not an integer"),
        ("heads", 0, r"heads 0 is not an integer"),
        ("layers", "4", r"layers '4' is not an integer"),
        ("height", 1 << 20, r"height 1048576 is not an integer in \[1, 8192\]"),
    ],
)
def test_an_observation_checkpoint_config_out_of_bounds_is_refused_before_the_model_is_built(tmp_path, field, value, named):
    config = {**OBS_PRESETS["tiny"].to_json(), field: value}
    ckpt = _checkpoint(tmp_path, "observation_config", config, "observation")
    with pytest.raises(ValueError, match=named) as err:
        load_model(ckpt)
    assert str(ckpt / "meta.json") in str(err.value)


def test_the_memory_check_names_the_model_and_both_sizes():
    check_memory(1000, "small", limit=4000)
    with pytest.raises(
        ValueError, match=r"big: about 1,001 parameters, 0.0 GiB of float32 weights, more than this machine's 0.0 GiB"
    ):
        check_memory(1001, "big", limit=4000)
