"""Config loading, overrides and validation."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from mutualslam_cli.config import CONFIG_DIR, RunConfig, load_config, to_dict, with_overrides
from mutualslam_cli.errors import ConfigError


def test_paper_yaml_equals_dataclass_defaults():
    # configs/paper.yaml must hold exactly the paper's values, which are the dataclass defaults.
    assert to_dict(load_config(CONFIG_DIR / "paper.yaml")) == to_dict(RunConfig())


def test_paper_values():
    c = load_config(CONFIG_DIR / "paper.yaml")
    assert (c.adapt.lambda_sparse, c.adapt.lambda_smooth, c.adapt.alpha) == (0.1, 0.1, 0.85)
    assert (c.adapt.lr, c.adapt.steps_per_keyframe) == (1e-3, 8)  # the paper's lr; steps: the paper is silent
    assert (c.adapt.ewc_beta, c.adapt.ewc_max_f) == (5e7, 1e-3)
    assert (c.adapt.mas_lambda, c.adapt.si_lambda) == (43.0, 240.0)  # departures, measured: bench/strength.py
    assert (c.adapt.validate_every, c.adapt.patience, c.adapt.tau_val) == (5, 3, 0.2)
    assert (c.vo.grid_size, c.vo.max_fts, c.vo.core_kfs) == (20, 500, 5)
    assert (c.ba.gamma, c.ba.d_max, c.ba.pattern, c.ba.max_targets) == (0.5, 1.5, "square3", 5)
    assert (c.net.width, c.net.height, c.net.min_depth, c.net.max_depth) == (640, 192, 0.1, 100.0)


def test_overrides_parse_yaml_values():
    c = load_config(CONFIG_DIR / "smoke.yaml", ["adapt.lr=1e-4", "vo.mode=svo", "eval.save_weights=true"])
    assert c.adapt.lr == 1e-4
    assert c.vo.mode == "svo"
    assert c.eval.save_weights is True
    assert c.net.width == 96  # from smoke.yaml


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("adapt.lrr=1", "unknown key"),
        ("vo.mode=foo", "not one of"),
        ("adapt.lr=abc", "expected a number"),
        ("adapt.lr=.nan", "NaN"),
        ("net.width=100", "a multiple of 32"),
        ("adapt.validate_every=0", "≥ 1"),
        ("seed=1.5", "integer"),
        ("nosection", "key=value"),
    ],
)
def test_bad_overrides_raise_config_error(override, message):
    with pytest.raises(ConfigError, match=message):
        load_config(None, [override])


def test_bad_files(tmp_path: Path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("adapt: [1, 2\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(bad)
    scalar = tmp_path / "scalar.yaml"
    scalar.write_text("42\n")
    with pytest.raises(ConfigError, match="mapping"):
        load_config(scalar)


def test_resolved_config_round_trips(tmp_path: Path):
    c = with_overrides(load_config(), adapt={"scheme": "replay+si"}, seed=3)
    p = tmp_path / "config.yaml"
    p.write_text(yaml.safe_dump(to_dict(c)))
    assert load_config(p) == c


def test_bare_on_off_reach_the_on_off_options_although_yaml_reads_them_as_booleans(tmp_path):
    assert load_config(None, ["net.fast=off"]).net.fast == "off"
    assert load_config(None, ["net.fast=on"]).net.fast == "on"
    f = tmp_path / "c.yaml"
    f.write_text("net:\n  fast: off\n")
    assert load_config(f).net.fast == "off"
    with pytest.raises(ConfigError):
        load_config(None, ["net.runtime=off"])


def test_experiment_section_lists_and_variants_are_checked(tmp_path):
    from mutualslam_cli.config import with_settings

    experiments = [*sorted(CONFIG_DIR.glob("table*.yaml")), *sorted(CONFIG_DIR.glob("figure*.yaml")),
                   CONFIG_DIR / "frontier.yaml"]
    for f in experiments:
        cfg = load_config(f)
        assert cfg.experiment.name == f.stem
        assert cfg.experiment.schemes
        assert cfg.experiment.seeds == [0, 1, 2]
        assert to_dict(cfg)["vo"] == to_dict(RunConfig())["vo"]  # everything else is the paper's
        for overrides in cfg.experiment.variants.values():
            with_settings(cfg, overrides)  # each variant is a valid config
    t5 = load_config(CONFIG_DIR / "table5_map.yaml")
    assert t5.experiment.variants["fts120_no_culling"] == ["vo.max_fts=120", "ba.culling=false"]
    v = with_settings(t5, t5.experiment.variants["fts120_no_culling"])
    assert v.vo.max_fts == 120
    assert v.ba.culling is False
    assert t5.ba.culling is True
    bad = tmp_path / "bad.yaml"
    bad.write_text("experiment:\n  seeds: [0, x]\n")
    with pytest.raises(ConfigError, match=r"experiment.seeds\[1\]"):
        load_config(bad)
    bad.write_text("experiment:\n  schemes: replay\n")
    with pytest.raises(ConfigError, match="expected a list"):
        load_config(bad)
    with pytest.raises(ConfigError, match="not a config section"):
        with_settings(t5, ["seed.x=1"])
    assert yaml.safe_load(yaml.safe_dump(to_dict(t5)))["experiment"]["variants"]["fts120"] == ["vo.max_fts=120"]


@pytest.mark.parametrize(("override", "match"), [
    ("vo.min_tracked=3", r"vo.min_tracked = 3: expected an integer ≥ 6"),
    ("vo.grid_size=2", r"vo.grid_size = 2: expected an integer ≥ 4"),
    ("vo.inject_outliers=1.0", r"vo.inject_outliers = 1.0: expected a number in \[0, 1\)"),
    ("ba.nearby_slots=5", r"ba.nearby_slots = 5: expected in \[0, max_targets\) \(max_targets = 5\)"),
])
def test_values_the_tool_cannot_work_with_are_named(override, match):
    """One check per value, at load time: the message names the key, the value and what was expected."""
    with pytest.raises(ConfigError, match=match):
        load_config(None, [override])


def test_fast_config_changes_only_the_budget_and_the_bounds():
    fast, paper = to_dict(load_config(CONFIG_DIR / "fast.yaml")), to_dict(load_config(CONFIG_DIR / "paper.yaml"))
    changed = {f"{sec}.{k}" for sec, vals in paper.items() if isinstance(vals, dict)
               for k, v in vals.items() if fast[sec][k] != v}
    assert changed == {"adapt.freeze_stages", "adapt.val_max", "ba.window", "eval.online", "adapt.lr"}
    assert fast["adapt"]["scheme"] == "replay+ewc"
    assert fast["net"] == paper["net"]


def test_tuned_presets_name_the_data_they_were_tuned_on():
    """paper.yaml is tuned on nothing; tuned.yaml differs from it only in the learning rate it took from
    tum_fr1_xyz, and fast.yaml names the four windows its budget was chosen on (the book reads these lines)."""
    from mutualslam_cli.config import tuned_on

    assert tuned_on(CONFIG_DIR / "paper.yaml") == []
    assert tuned_on(CONFIG_DIR / "tuned.yaml") == ["tum_fr1_xyz"]
    assert tuned_on(CONFIG_DIR / "fast.yaml") == ["tum_fr1_xyz", "icl_lr_kt2", "tum_fr1_desk_loss", "tum_fr1_desk_9f"]
    tuned, paper = to_dict(load_config(CONFIG_DIR / "tuned.yaml")), to_dict(load_config(CONFIG_DIR / "paper.yaml"))
    changed = {f"{sec}.{k}" for sec, vals in paper.items() if isinstance(vals, dict)
               for k, v in vals.items() if tuned[sec][k] != v}
    assert changed == {"adapt.lr"}
    assert tuned["adapt"]["lr"] == 1e-4
    assert paper["adapt"]["lr"] == 1e-3


def test_the_default_is_the_papers_method_made_robust_and_names_what_chose_it():
    """Without --config a command reads configs/default.yaml: the paper's values but for the scale alignment and the
    trust region (README "Adapting without picking a rate"), chosen on two shared windows its header names."""
    from mutualslam_cli.config import DEFAULT_CONFIG, tuned_on

    assert DEFAULT_CONFIG == CONFIG_DIR / "default.yaml"
    default, paper = to_dict(load_config()), to_dict(load_config(CONFIG_DIR / "paper.yaml"))
    changed = {f"{sec}.{k}": vals[k] for sec, vals in default.items() if isinstance(vals, dict)
               for k in vals if paper[sec][k] != vals[k]}
    assert changed == {"adapt.scale": "align_batch", "adapt.trust": 3e-3}
    assert (paper["adapt"]["scale"], paper["adapt"]["trust"], paper["adapt"]["average"]) == ("learn", 0.0, 0.0)
    assert paper["adapt"]["encoder_lr"] == 1.0
    assert tuned_on(DEFAULT_CONFIG) == ["tum_fr1_xyz", "icl_lr_kt2"]


def test_a_preset_without_a_tuned_on_line_is_unknown(tmp_path: Path):
    from mutualslam_cli.config import tuned_on

    f = tmp_path / "mine.yaml"
    f.write_text("adapt:\n  lr: 1.0e-4\n")
    assert tuned_on(f) is None  # unknown: the book treats it as tuned on everything it reports
