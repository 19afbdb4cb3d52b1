"""PerturbConfig: presets, serialisation, scaling, validation; what `perturb` accepts."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import morphgs
from morphgs import PerturbConfig
from morphgs.perturb import as_config


def test_defaults_are_the_papers() -> None:
    c = PerturbConfig()
    assert c.to_dict() == {
        "position_jitter": 0.002, "color_noise": 0.05, "opacity_noise": 0.05,
        "prune": 0.5, "scale_noise": 0.01, "rotation_noise": 0.01,
    }


@pytest.mark.parametrize(
    ("name", "enabled"),
    [
        ("spatial", ("position_jitter",)),
        ("radiometric", ("color_noise", "opacity_noise")),
        ("morphological", ("prune", "scale_noise", "rotation_noise")),
        ("naive", ("position_jitter", "color_noise", "opacity_noise", "prune", "scale_noise",
                   "rotation_noise")),
    ],
)
def test_presets_enable_their_category_at_paper_defaults(name: str, enabled: tuple) -> None:
    c = PerturbConfig.preset(name)
    assert c.name == name and c.enabled == enabled
    paper = PerturbConfig().to_dict()
    for field, value in c.to_dict().items():
        assert value == (paper[field] if field in enabled else None)


def test_unknown_preset_lists_the_valid_ones() -> None:
    with pytest.raises(ValueError, match="blur.*spatial, radiometric, morphological, naive"):
        PerturbConfig.preset("blur")


@pytest.mark.parametrize("name", ["spatial", "radiometric", "morphological", "naive"])
def test_dict_and_json_round_trips(name: str) -> None:
    c = PerturbConfig.preset(name)
    assert PerturbConfig.from_dict(c.to_dict()) == c
    assert PerturbConfig.from_json(c.to_json()) == c
    custom = PerturbConfig(position_jitter=None, color_noise=0.123, prune=0.25)
    assert PerturbConfig.from_json(custom.to_json()) == custom


def test_from_dict_rejects_unknown_keys_and_missing_keys_disable() -> None:
    with pytest.raises(ValueError, match="'prun'.*valid fields: position_jitter"):
        PerturbConfig.from_dict({"prun": 0.5})
    assert PerturbConfig.from_dict({"prune": 0.2}).enabled == ("prune",)
    with pytest.raises(ValueError, match="JSON object"):
        PerturbConfig.from_json("[1, 2]")


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"scale_noise": -0.01}, "scale_noise"),
        ({"color_noise": float("nan")}, "color_noise"),
        ({"position_jitter": float("inf")}, "position_jitter"),
        ({"prune": 1.5}, "prune"),
        ({"prune": -0.1}, "prune"),
        ({"prune": float("nan")}, "prune"),
    ],
)
def test_invalid_values_raise_value_error_naming_the_field(kwargs: dict, field: str) -> None:
    with pytest.raises(ValueError, match=f"^{field}"):
        PerturbConfig(**kwargs)


def test_non_numbers_raise_type_error() -> None:
    with pytest.raises(TypeError, match="opacity_noise"):
        PerturbConfig(opacity_noise="0.1")  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="prune"):
        PerturbConfig(prune=True)


def test_config_is_frozen_and_hashable() -> None:
    c = PerturbConfig.preset("naive")
    with pytest.raises(dataclasses.FrozenInstanceError):
        c.prune = 0.1  # type: ignore[misc]
    assert hash(c) == hash(PerturbConfig())


def test_scaled_multiplies_noise_and_clips_prune() -> None:
    c = PerturbConfig.preset("morphological")
    d = c.scaled(2.0).to_dict()
    assert d["scale_noise"] == pytest.approx(0.02) and d["rotation_noise"] == pytest.approx(0.02)
    assert d["prune"] == 1.0 and d["position_jitter"] is None
    assert c.scaled(0.5).prune == 0.25
    zero = PerturbConfig().scaled(0)
    assert zero.enabled == ()
    assert c.scaled(1.0) == c
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="^k must"):
            c.scaled(bad)


def test_as_config_accepts_name_config_and_dict() -> None:
    c = PerturbConfig(prune=0.1)
    assert as_config(c) is c
    assert as_config("spatial") == PerturbConfig.preset("spatial")
    assert as_config({"color_noise": 0.2}) == PerturbConfig.from_dict({"color_noise": 0.2})
    with pytest.raises(TypeError, match="preset name"):
        as_config(3)  # type: ignore[arg-type]


def _scene() -> morphgs.GaussianScene:
    rng = np.random.default_rng(0)
    return morphgs.GaussianScene.from_arrays(
        means=rng.normal(size=(100, 3)), quats=rng.normal(size=(100, 4)),
        log_scales=np.zeros((100, 3)), opacity_logits=np.zeros(100), sh0=np.zeros((100, 3)),
    )


def test_perturb_accepts_every_config_form_and_defaults_to_morphological() -> None:
    s = _scene()
    ref = morphgs.perturb(s, PerturbConfig.preset("morphological"), seed=4)
    for cfg in ("morphological", PerturbConfig.preset("morphological").to_dict()):
        np.testing.assert_array_equal(morphgs.perturb(s, cfg, seed=4).quats, ref.quats)
    np.testing.assert_array_equal(morphgs.perturb(s, seed=4).quats, ref.quats)


def test_perturb_validates_seed_and_arguments() -> None:
    s = _scene()
    with pytest.raises(TypeError):
        morphgs.perturb(s, "naive")  # type: ignore[call-overload]
    with pytest.raises(ValueError, match="seed"):
        morphgs.perturb(s, seed=-1)
    with pytest.raises(ValueError, match="seed"):
        morphgs.perturb(s, seed=2**64)
    with pytest.raises(TypeError, match="seed"):
        morphgs.perturb(s, seed=1.5)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="seed"):
        morphgs.perturb(s, seed=True)
    assert len(morphgs.perturb(s, "spatial", seed=np.uint64(2**64 - 1))) == 100
    with pytest.raises(ValueError, match="unknown preset"):
        morphgs.perturb(s, "blurry", seed=1)
    with pytest.raises(TypeError, match="GaussianScene"):
        morphgs.perturb(np.zeros(3), seed=1)  # type: ignore[call-overload]


def test_native_entry_point_validates_too() -> None:
    from morphgs._core import _perturb

    s = _scene()
    none = dict(position_jitter=None, color_noise=None, opacity_noise=None, prune=None,
                scale_noise=None, rotation_noise=None)
    with pytest.raises(ValueError, match="^rotation_noise"):
        _perturb(s, **{**none, "rotation_noise": -1.0}, seed=0)
    with pytest.raises(ValueError, match="^prune"):
        _perturb(s, **{**none, "prune": 2.0}, seed=0)
