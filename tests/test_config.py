"""The training configuration (engine.train.config): groups, old names, and no dead settings."""
from __future__ import annotations

import dataclasses
import re

import pytest

from engine.train.config import FLAT_NAMES, GROUPS, TrainConfig, apply_overrides, get_preset, setting_names


def test_settings_are_few_and_grouped():
    names = setting_names()
    assert len(names) <= 90 and len(set(names)) == len(names)
    assert [f.name for f in dataclasses.fields(TrainConfig)] == list(GROUPS)


def test_every_setting_is_read_by_the_code(repo_root):
    """No field that nothing reads: each ``group.field`` is read as ``.group.field`` in the engine,
    the add-on or the operators; the Gaussians' and the field's own settings as ``cfg.field`` in the
    scene module that owns them."""
    code = "\n".join(p.read_text() for d in ("engine", "operators", "bt4d_addon")
                     for p in (repo_root / d).rglob("*.py"))
    owners = {"gaussians": "engine/scene/gaussians.py", "hexplane": "engine/scene/deformation.py"}

    def read(name):
        group, leaf = name.split(".")
        if re.search(r"\." + re.escape(name) + r"\b", code):
            return True
        return group in owners and re.search(r"\bcfg\." + leaf + r"\b", (repo_root / owners[group]).read_text())

    unread = [n for n in setting_names() if not read(n)]
    assert not unread, unread


def test_old_flat_names_load_and_set():
    old = {"iterations": 7, "max_gaussians": 500, "motion": "hexplane", "lambda_cover": 0.0,
           "spike_flow_prefetch": 0, "lambda_along_ray": 1.0}  # the last two are no longer settings
    cfg = TrainConfig.from_dict(old)
    assert (cfg.schedule.iterations, cfg.densify.max_gaussians, cfg.motion.representation, cfg.losses.cover) == \
        (7, 500, "hexplane", 0.0)
    assert TrainConfig.from_dict(cfg.to_dict()) == cfg
    assert get_preset("fast", {"max_gaussians": 500}) == get_preset("fast", {"densify.max_gaussians": 500})
    assert all(n in setting_names() for n in FLAT_NAMES.values())


def test_bad_names_and_values_say_what_is_wrong():
    with pytest.raises(KeyError, match="did you mean 'densify.max_gaussians'"):
        get_preset("fast", {"densify.max_gausians": 1})
    with pytest.raises(ValueError, match="skip.early_stop"):
        get_preset("fast", {"skip.early_stop": "perhaps"})
    assert get_preset("fast", {"skip.early_stop": "on"}).skip.early_stop is True
    with pytest.raises(KeyError, match="unknown preset"):
        get_preset("ultra")


def test_overrides_never_share_groups_with_the_original():
    base = get_preset("fast")
    new = apply_overrides(base, {"schedule.iterations": 5})
    new.densify.max_gaussians = 1
    assert base.densify.max_gaussians == 20000 and base.schedule.iterations == 1000
