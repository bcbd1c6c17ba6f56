"""Params overrides, config files and the content-keyed stage cache."""

from __future__ import annotations

import json
import pickle
from dataclasses import dataclass

import numpy as np
import pytest

from nuplan_occ.pipeline.cache import StageCache, stable_hash
from nuplan_occ.cli.app import _build_params
from nuplan_occ.pipeline.params import (ConfigError, apply_overrides, check_params, default_params, load_config_file,
                                       param_rows, parse_set_options)
from nuplan_occ.stages import PIPELINE


@dataclass(frozen=True)
class _Params:
    margin: float = 1.1
    method: str = "knn"
    enabled: bool = True
    count: int = 3


def test_overrides_coerce_types_and_reject_unknown_names(tmp_path):
    params = {"split": _Params()}
    out = apply_overrides(params, parse_set_options(["split.margin=1.25", "split.enabled=false", "split.count=7"]), "--set")
    assert out["split"] == _Params(margin=1.25, enabled=False, count=7)
    with pytest.raises(ConfigError, match="unknown stage 'splat'"):
        apply_overrides(params, {"splat": {"margin": 1}}, "cfg")
    with pytest.raises(ConfigError, match="has no param 'margn'"):
        apply_overrides(params, {"split": {"margn": 1}}, "cfg")
    with pytest.raises(ConfigError, match="expected a number"):
        apply_overrides(params, {"split": {"margin": "wide"}}, "cfg")
    with pytest.raises(ConfigError, match="STAGE.PARAM=VALUE"):
        parse_set_options(["margin=1"])


def test_config_files_json_and_toml(tmp_path):
    (tmp_path / "c.json").write_text(json.dumps({"split": {"method": "global"}}))
    (tmp_path / "c.toml").write_text('[split]\nmargin = 1.5\n')
    (tmp_path / "bad.json").write_text("{not json")
    assert load_config_file(tmp_path / "c.json") == {"split": {"method": "global"}}
    assert load_config_file(tmp_path / "c.toml") == {"split": {"margin": 1.5}}
    with pytest.raises(ConfigError, match="bad.json"):
        load_config_file(tmp_path / "bad.json")


def test_stable_hash_depends_on_params_and_is_order_free():
    assert stable_hash("s", _Params()) == stable_hash("s", _Params())
    assert stable_hash("s", _Params()) != stable_hash("s", _Params(margin=1.2))
    assert stable_hash({"a": 1, "b": 2}) == stable_hash({"b": 2, "a": 1})


def test_cache_round_trip_and_damaged_entry_counts_as_absent(tmp_path):
    cache = StageCache(tmp_path)
    assert cache.get("split", "k") is None
    cache.put("split", "k", {"x": [1, 2, 3]})
    assert cache.get("split", "k") == {"x": [1, 2, 3]}
    (tmp_path / "split" / "k.pkl.zst").write_bytes(b"garbage")
    assert cache.get("split", "k") is None
    assert not list((tmp_path / "split").glob(".*.tmp"))


def test_an_output_stored_item_by_item_reads_back_one_element_per_access(tmp_path):
    cache = StageCache(tmp_path)
    sweeps = [np.arange(3000, dtype=np.float32).reshape(-1, 3) + k for k in range(4)] + [None]
    readers = cache.put("filter", "k", {"background": sweeps, "outliers_removed": [1, 2, 3, 4, 0]},
                        item_outputs=("background",))
    for outputs in (readers, cache.get("filter", "k")):
        stored = outputs["background"]
        assert len(stored) == 5 and stored[4] is None and stored[-1] is None
        np.testing.assert_array_equal(stored[2], sweeps[2])
        assert stored[2] is not stored[2]  # read on every access, nothing kept
        assert [s is None for s in stored] == [False] * 4 + [True]
        with pytest.raises(IndexError):
            stored[5]
    assert cache.get("filter", "k")["outliers_removed"] == [1, 2, 3, 4, 0]
    assert pickle.loads(pickle.dumps(readers["background"]))[:1][0].tolist() == sweeps[0].tolist()
    items = tmp_path / "filter" / "k.background.items"
    items.write_bytes(items.read_bytes()[:-10])  # a damaged (truncated) item file: the entry counts as absent
    assert cache.get("filter", "k") is None


def test_every_stage_param_is_declared_with_a_meaning_and_its_default_passes_its_own_checks():
    for section, value in default_params(PIPELINE).items():
        rows = param_rows(type(value))
        assert rows and all(row["meaning"] for row in rows), section
        check_params(value, section)
    readers = {stage.params_name for stage in PIPELINE}
    assert readers == set(default_params(PIPELINE))  # every section read is declared by one stage


def test_a_tuple_param_from_set_is_a_tuple_of_its_element_type():
    params = _build_params(None, ["register.max_correspondence_m=1.0,0.5", "aggregate.rigid_categories=vehicle"], None)
    assert params["register"].max_correspondence_m == (1.0, 0.5)
    assert params["aggregate"].rigid_categories == ("vehicle",)


def test_a_config_files_rate_is_not_overwritten_by_the_cli_default(tmp_path):
    config = tmp_path / "my.toml"
    config.write_text("[load]\nrate_hz = 5.0\n")
    assert _build_params(config, [], None)["load"].rate_hz == 5.0
    assert _build_params(config, [], 2.0)["load"].rate_hz == 2.0  # given on the command line: it wins
    assert _build_params(None, [], None)["load"].rate_hz == 10.0


@pytest.mark.parametrize("override, message", [
    ({"filter": {"std_ratio": "nan"}}, "not a finite number"),
    ({"filter": {"std_ratio": -1.0}}, "below the allowed range"),
    ({"filter": {"nb_neighbors": 8.9}}, "expected a whole number"),
    ({"visibility": {"lidar": 2}}, "expected true or false"),
    ({"filter": {"method": 5}}, "expected text"),
    ({"reconstruct": {"method": "marching"}}, "is not one of"),
    ({"aggregate": {"rigid_categories": "vehicle,spaceship"}}, "'spaceship' is not one of"),
    ({"write": {"members": "semantics,bogus"}}, "'bogus' is not one of"),
    ({"load": {"rate_hz": 0}}, "below the allowed range"),
    ({"load": {"rate_hz": -10}}, "below the allowed range"),
    ({"load": {"rate_hz": 40}}, "exceeds the sweep rate"),
])
def test_bad_values_fail_at_parse_time_naming_the_source(override, message):
    with pytest.raises(ConfigError, match=message) as raised:
        apply_overrides(default_params(PIPELINE), override, "my.toml")
    assert str(raised.value).startswith("my.toml: ")
