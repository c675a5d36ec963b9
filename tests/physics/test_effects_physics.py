"""The detector-effects configuration (physics/effects.py): names, presets, config, overrides."""
import json

import numpy as np
import pytest

from slicersim.errors import EffectsError
from slicersim.physics import cosmic_rays as cr
from slicersim.physics.effects import EFFECT_NAMES, STREAMS, DetectorEffects, check_number, parameter_class


def test_from_names():
    e = DetectorEffects.from_names("ipc, cosmic_rays")
    assert e.enabled == ("cosmic_rays", "ipc")                    # canonical order
    assert e == DetectorEffects.from_names(["cosmic_rays", "ipc"])
    assert e.params("ipc").alpha == 0.016 and "ipc" in e and "nonlinearity" not in e
    assert not DetectorEffects.from_names("") and not DetectorEffects.from_names(None)
    all_ = DetectorEffects.from_names("all")
    assert all_.enabled == tuple(n for n in EFFECT_NAMES if n != "persistence")
    assert "persistence" in DetectorEffects.from_names("all", has_previous_charge=True)
    assert "persistence" in DetectorEffects.from_names("persistence")
    with pytest.raises(EffectsError, match=r"unknown effect 'cosmic_ray' \(did you mean 'cosmic_rays'\?\); valid: 'cosmic_rays', 'ipc'"):
        DetectorEffects.from_names("cosmic_ray")
    with pytest.raises(EffectsError, match="not enabled"):
        e.params("nonlinearity")


def test_preset_lazuli_and_config_round_trip():
    e = DetectorEffects.preset("lazuli")
    assert e.enabled == DetectorEffects.from_names("all").enabled
    assert e.params("cosmic_rays").rate == 5.0
    cfg = e.to_config()
    text = json.dumps(cfg)                                        # JSON-able
    back = DetectorEffects.from_config(json.loads(text))
    assert back == e and back.to_config() == cfg
    assert DetectorEffects.from_config(cfg["effects"]) == e      # the table itself
    with pytest.raises(EffectsError, match="preset"):
        DetectorEffects.preset("euclid")


def test_config_values_and_errors():
    cfg = {"effects": {"enabled": "cosmic_rays,ipc", "cosmic_rays": {"rate": 8.0, "thickness": 8.0},
                       "ipc": {"kernel": [[0, 0.01, 0], [0.01, 0.96, 0.01], [0, 0.01, 0]]},
                       "nonlinearity": {"deficit": 0.03}}}          # disabled: validated, dropped
    e = DetectorEffects.from_config(cfg)
    assert e.enabled == ("cosmic_rays", "ipc")
    assert e.params("cosmic_rays").rate == 8.0 and e.params("cosmic_rays").thickness == 8.0
    assert e.params("ipc").matrix()[1, 1] == 0.96
    assert DetectorEffects.from_config(e.to_config()) == e
    bad = [{"effects": {"enabled": ["ipc"], "ipc": {"alfa": 0.01}}},                 # unknown parameter
           {"effects": {"enabled": ["ipc"], "cosmic": {}}},                           # unknown section
           {"effects": {"enabled": ["ipc"], "nonlinearity": {"deficit": -0.1}}},      # disabled but invalid
           {"effects": {"enabled": ["warp"]}},
           {"effects": {"enabled": ["cosmic_rays"], "cosmic_rays": {"rate": -5}}},
           {"effects": {"enabled": ["bad_pixels"], "bad_pixels": {"hot_fraction": 0.7, "warm_fraction": 0.7}}},
           {"effects": {"enabled": ["ipc"], "ipc": {"kernel": [[0.5] * 3] * 3}}},
           {"effects": {"enabled": ["ipc"], "ipc": 3}}, {"effects": 5}]
    for c in bad:
        with pytest.raises(EffectsError):
            DetectorEffects.from_config(c)


def test_cr_rate_override():
    e = DetectorEffects.from_names("cosmic_rays,bad_pixels").with_overrides(cr_rate=12.5)
    assert e.params("cosmic_rays").rate == 12.5 and "bad_pixels" in e
    assert DetectorEffects.from_names("cosmic_rays").with_overrides().params("cosmic_rays").rate == 5.0
    with pytest.raises(EffectsError, match="cr-rate"):
        DetectorEffects.from_names("ipc").with_overrides(cr_rate=3.0)
    with pytest.raises(EffectsError, match="rate"):
        DetectorEffects.from_names("cosmic_rays").with_overrides(cr_rate=-1.0)


def test_cosmic_rays_independent_of_other_effects_and_order():
    """Counter-based streams: the CR deposits depend only on (seed, ramp, frames, CR parameters)."""
    a = DetectorEffects.from_names("cosmic_rays")
    b = DetectorEffects.from_names("bad_pixels,nonlinearity,cosmic_rays,ipc")
    da = cr.cosmic_ray_deposits(4, 0, 32, 2.83, (2048, 2048), a.params("cosmic_rays"))
    db = cr.cosmic_ray_deposits(4, 0, 32, 2.83, (2048, 2048), b.params("cosmic_rays"))
    np.testing.assert_array_equal(da, db)


def test_streams_disjoint_from_plain_ramp():
    bases = sorted(STREAMS.values())
    assert all(b2 - b1 >= 2 ** 24 for b1, b2 in zip(bases, bases[1:]))
    assert min(bases) >= 4 * 2 ** 26                               # plain ramp: 4·ramp + p < 2**28
    assert max(bases) + 2 ** 24 <= 0x80000000                      # below the PTRS offset


def test_every_effect_has_a_validated_parameter_class():
    for name in EFFECT_NAMES:
        cls = parameter_class(name)
        cls()                                                      # defaults valid
    with pytest.raises(EffectsError):
        parameter_class("dust")
    with pytest.raises(EffectsError, match="rate"):
        check_number("rate", -1)
    with pytest.raises(EffectsError):
        check_number("x", True)


@pytest.mark.parametrize("config", [
    {"effects": {"enabled": ["ipc"]}, "ipc": {"alpha": 0.2}},            # JSON with the table beside "effects"
    {"effects": {"enabled": ["ipc"]}, "ipc": {"alpha": float("nan")}},   # TOML [ipc] after [effects]
    {"effects": {"enabled": ["ipc"]}, "ipcc": {}},                       # a misspelt effect table
    {"effects": {"enabled": ["cosmic_rays"]}, "cosmic_rays": {"rate": 1e300}},
])
def test_effect_tables_outside_the_effects_table_are_refused(config):
    """[ipc] beside [effects] (instead of [effects.ipc]) was silently ignored: the defaults were used."""
    with pytest.raises(EffectsError, match=r"outside \[effects\]: write them as \[effects.NAME\]"):
        DetectorEffects.from_config(config)
    inside = {"effects": {"enabled": ["ipc"], "ipc": {"alpha": 0.01}}, "detector": {}}
    assert DetectorEffects.from_config(inside)     # other tables of a whole configuration stay allowed
