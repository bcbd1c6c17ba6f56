"""Params overrides, config files and the content-keyed stage cache."""

from __future__ import annotations

import json
import pickle
from dataclasses import dataclass

import numpy as np
import pytest

from nuplan_occ.pipeline.cache import StageCache, stable_hash
from nuplan_occ.pipeline.params import ConfigError, apply_overrides, load_config_file, parse_set_options


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
    with pytest.raises(ConfigError, match="expected float"):
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
