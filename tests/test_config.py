"""The config tree: presets, TOML round trip, typed overrides and the errors that name the key."""

from __future__ import annotations

import pytest

from s3o_warp.config import PRESETS, Config, check, make_config, to_dict, to_toml
from s3o_warp.data.io import write_text
from s3o_warp.errors import ConfigError


@pytest.mark.parametrize("preset", list(PRESETS))
def test_every_preset_resolves_and_round_trips(preset, tmp_path):
    cfg = make_config(preset)
    assert cfg.preset == preset
    write_text(tmp_path / "config.toml", to_toml(cfg))
    again = make_config("default", tmp_path / "config.toml")
    assert to_dict(again) == to_dict(cfg)


def test_precedence_defaults_preset_toml_flags(tmp_path):
    (tmp_path / "c.toml").write_text("[motion]\nsteps = 11\nwarmup_steps = 3\n")
    cfg = make_config("fast", tmp_path / "c.toml", ["motion.steps=12"], seed=5)
    assert cfg.data.crop_size == PRESETS["fast"][1]["data.crop_size"]
    assert cfg.motion.warmup_steps == 3
    assert cfg.motion.steps == 12
    assert cfg.seed == 5
    assert Config().motion.steps != 12


@pytest.mark.parametrize(
    "override, match",
    [
        ("motion.stepz=3", "unknown config key 'motion.stepz'"),
        ("nosuch.key=1", "unknown config key 'nosuch.key'"),
        ("motion.steps=abc", "'motion.steps' must be int"),
        ("motion.w_sil=yes", "'motion.w_sil' must be float"),
        ("output.render_video=maybe", "'output.render_video' must be bool"),
        ("motion.steps", "must look like section.key=value"),
    ],
)
def test_bad_overrides_name_the_key(override, match):
    with pytest.raises(ConfigError, match=match):
        make_config("default", overrides=[override])


def test_bad_toml_names_the_file_and_key(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[motion]\nsteps = 'many'\n")
    with pytest.raises(ConfigError, match="'motion.steps' must be int"):
        make_config("default", bad)
    bad.write_text("[motion\n")
    with pytest.raises(ConfigError, match="bad.toml"):
        make_config("default", bad)
    with pytest.raises(ConfigError, match="does not exist"):
        make_config("default", tmp_path / "missing.toml")
    with pytest.raises(ConfigError, match="unknown preset"):
        make_config("turbo")


def test_the_config_imports_nothing_of_the_method():
    """config.py sits at the bottom of the imports: reading settings loads no part of the method (only the errors)."""
    import subprocess
    import sys

    code = "import sys, s3o_warp.config; print(sorted(m for m in sys.modules if m.startswith('s3o_warp.')))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "['s3o_warp.config', 's3o_warp.errors']", out


def _bad_values():
    """(key, a value outside its choices or range) for every setting that has choices or a range."""
    from s3o_warp.config import _parts, _settings

    out = []
    for key, _owner, _name, hint in _settings(Config()):
        _base, choices, bounds, _optional = _parts(hint)
        if choices is not None:
            out.append((key, "nosuch"))
        if bounds is not None and bounds.lo is not None:
            out.append((key, bounds.lo if bounds.lo_open else bounds.lo - 1))
        if bounds is not None and bounds.hi is not None:
            out.append((key, bounds.hi if bounds.hi_open else bounds.hi + 1))
    return out


@pytest.mark.parametrize("key, value", _bad_values())
def test_every_choice_and_range_is_refused_naming_the_key(key, value):
    with pytest.raises(ConfigError, match=rf"config key '{key}' must be "):
        make_config("default", overrides=[f"{key}={value}"])


def _numeric_settings():
    from s3o_warp.config import _parts, _settings

    return [(key, _parts(hint)) for key, _owner, _name, hint in _settings(Config())
            if _parts(hint)[0] in (int, float)]


def test_every_numeric_setting_has_a_range():
    assert [key for key, (_base, _choices, bounds, _optional) in _numeric_settings() if bounds is None] == []


@pytest.mark.parametrize("key", [key for key, parts in _numeric_settings() if parts[0] is float])
def test_inf_and_nan_are_refused_for_every_float_setting(key, tmp_path):
    for value in ("inf", "-inf", "nan"):
        with pytest.raises(ConfigError, match=rf"config key '{key}' must be a finite number, got {value}"):
            make_config("default", overrides=[f"{key}={value}"])
    section, name = key.split(".") if "." in key else ("", key)
    (tmp_path / "c.toml").write_text(f"[{section}]\n{name} = inf\n" if section else f"{name} = inf\n")
    with pytest.raises(ConfigError, match=rf"'{key}' must be a finite number"):
        make_config("default", tmp_path / "c.toml")


@pytest.mark.parametrize("override, match", [
    ("motion.turn_rate=-45", r"'motion.turn_rate' must be >= -30 and <= 30, got -45.0"),
    ("motion.hypothesis_max_rate=90", r"'motion.hypothesis_max_rate' must be >= 0 and <= 30"),
    ("motion.lr_shape=-0.001", r"'motion.lr_shape' must be >= 0"),
    ("seed=4294967296", r"'seed' must be >= 0 and <= 4294967295"),
])
def test_a_value_no_user_means_is_refused(override, match):
    with pytest.raises(ConfigError, match=match):
        make_config("default", overrides=[override])
    assert make_config("default", overrides=["motion.turn_rate=-2.5", "motion.turn_rate=none"]).motion.turn_rate is None


def test_a_config_changed_in_code_is_checked_too():
    cfg = make_config("default")
    cfg.motion.rigidity = "elastic"
    with pytest.raises(ConfigError, match="'motion.rigidity' must be one of 'dynamic', 'arap', 'none'"):
        check(cfg)
    cfg = make_config("default")
    cfg.motion.lr_shape = float("nan")
    with pytest.raises(ConfigError, match="'motion.lr_shape' must be a finite number, got nan"):
        check(cfg)
    cfg = make_config("default")
    cfg.motion.resample_vertices = 5
    with pytest.raises(ConfigError, match="'motion.resample_vertices' must be 0"):
        check(cfg)


def test_the_settings_are_the_ones_a_user_sets():
    from s3o_warp.config import _settings

    assert len(list(_settings(Config()))) < 70


def test_a_bad_setting_writes_nothing(tiny_sequence, tmp_path, capsys):
    """The command line and a fit given a Config built in code both stop before any work: no run directory."""
    import torch

    from s3o_warp.cli import main
    from s3o_warp.fit import fit

    out = tmp_path / "run"
    rc = main([str(tiny_sequence), "--out", str(out), "--device", "cpu", "--set", "motion.principal_point=centre"])
    assert rc == 2 and not out.exists()
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "motion.principal_point" in err[0] and "'frame', 'shared'" in err[0]
    cfg = make_config("smoke")
    cfg.skeleton.t_o = 1.5
    with pytest.raises(ConfigError, match="skeleton.t_o"):
        fit(tiny_sequence, out, cfg, torch.device("cpu"))
    assert not out.exists()
