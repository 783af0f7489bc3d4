"""RPR configs extend each other with ``base:``: the shipped ones resolve exactly as before they were rewritten,
and users' configs get the same mechanism (relative paths, names in configs/rpr, chains, clear errors)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from mapfree.rpr.config import RPRConfig, config_dir, load_config
from mapfree.yamlio import deep_merge, read_yaml_with_base

#: Every config in configs/rpr as written out in full at b9f3c3b, before ``base:`` existed (parsed YAML as JSON).
FULL_CONFIGS = Path(__file__).resolve().parent / "data" / "rpr_configs_full.json"


def test_every_shipped_config_resolves_as_its_full_version_did():
    full = json.loads(FULL_CONFIGS.read_text())
    based = 0
    for name, old in sorted(full.items()):
        path = config_dir() / name
        assert path.is_file(), f"{name} was shipped before and is gone"
        assert "base" not in old
        based += "base" in yaml.safe_load(path.read_text())
        assert read_yaml_with_base(path, (config_dir(),)) == old, name  # same keys, same values: no defaults relied on
        assert load_config(path).to_dict() == RPRConfig.from_dict(old).validate().to_dict(), name
    assert len(full) == 14 and based >= 11  # the 12 public configs (11 extend another) and ours


def test_deep_merge_merges_mappings_and_replaces_the_rest():
    base = {"model": {"rotation": "6d", "mlp": [256, 128], "position": True}, "name": "a"}
    out = deep_merge(base, {"model": {"mlp": [], "rotation": "quat"}, "loss": {"lam": 2}})
    assert out == {"model": {"rotation": "quat", "mlp": [], "position": True}, "name": "a", "loss": {"lam": 2}}
    assert base["model"]["mlp"] == [256, 128]  # the base is not modified


def test_user_config_extends_a_relative_file_and_a_shipped_name(tmp_path):
    (tmp_path / "sub").mkdir()
    (tmp_path / "common.yaml").write_text("base: 3d3d\ndata:\n  root: /data/x\n  batch_size: 4\n")
    (tmp_path / "sub" / "mine.yaml").write_text("base: ../common.yaml\nname: mine\ntrain:\n  lr: 1.0e-5\n")
    cfg = load_config(tmp_path / "sub" / "mine.yaml")
    ref = load_config(config_dir() / "3d3d.yaml")
    assert cfg.name == "mine" and cfg.train.lr == 1e-5 and cfg.data.batch_size == 4 and cfg.data.root == "/data/x"
    assert cfg.model == ref.model and cfg.loss == ref.loss  # from 3d3d (itself extending rot6d_trans)
    assert cfg.data.image_size == ref.data.image_size and cfg.train.adam_eps == ref.train.adam_eps == 1e-6


def test_base_errors_name_the_files(tmp_path, capsys):
    from mapfree.cli import main

    (tmp_path / "a.yaml").write_text("# a\nbase: b.yaml\nname: a\n")
    (tmp_path / "b.yaml").write_text("base: a.yaml\n")
    with pytest.raises(ValueError, match=r"base cycle: .*a\.yaml -> .*b\.yaml -> .*a\.yaml"):
        load_config(tmp_path / "a.yaml")
    assert main(["train", str(tmp_path / "a.yaml")]) == 1  # mapfree train: the same message, no traceback
    assert "base cycle" in capsys.readouterr().err
    (tmp_path / "self.yaml").write_text("base: self.yaml\n")
    with pytest.raises(ValueError, match="base cycle"):
        load_config(tmp_path / "self.yaml")
    (tmp_path / "c.yaml").write_text("name: c\n\nbase: nowhere.yaml\n")
    with pytest.raises(ValueError, match=r"c\.yaml:3: base 'nowhere\.yaml' not found .*nowhere\.yaml"):
        load_config(tmp_path / "c.yaml")
    (tmp_path / "d.yaml").write_text("base: [a.yaml]\n")
    with pytest.raises(ValueError, match=r"d\.yaml:1: base must name a YAML file"):
        load_config(tmp_path / "d.yaml")
    (tmp_path / "e.yaml").write_text("base: rot6d_trans\nmodel:\n  rotaton: quat\n")  # a typo in the child
    with pytest.raises(ValueError, match=r"e\.yaml.*unknown key\(s\) rotaton"):
        load_config(tmp_path / "e.yaml")
