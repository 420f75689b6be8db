"""The fast / balanced / accurate presets (conf/preset/, docs/tradeoff.md).

Each preset composes from the installed config package with ``+preset=<name>``,
changes only the documented knobs, builds a model whose networks have the
preset's sizes, and the three are ordered by cost.
"""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf
from torch.utils.flop_counter import FlopCounterMode

from nsd.model.build import build_model

PRESETS = ("fast", "balanced", "accurate")
# the knobs a preset may set (docs/tradeoff.md "Presets")
KNOBS = {
    "data.image_size",
    "model.crop_size",
    "model.num_windows",
    "model.encoder.widths",
    "model.decoder.widths",
    "model.decoder.convs",
}


def _cfg(overrides: list[str]):
    """The config with ``overrides``; ``model.num_windows`` the count ``auto`` settles on for
    the default scene (2), so that a model can be built without a scene."""
    with initialize_config_module("nsd.conf", version_base="1.3"):
        return compose("train", overrides=["model.num_windows=2", *overrides])


def _flat(d, prefix=""):
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flat(v, key + "."))
        else:
            out[key] = v
    return out


def _changed(preset: str) -> dict[str, object]:
    base = _flat(OmegaConf.to_container(_cfg([]), resolve=True))
    new = _flat(OmegaConf.to_container(_cfg([f"+preset={preset}"]), resolve=True))
    assert new.keys() == base.keys(), f"preset {preset} adds or removes config keys"
    return {k: new[k] for k in base if new[k] != base[k]}


@pytest.mark.parametrize("preset", PRESETS)
def test_preset_changes_only_documented_knobs(preset):
    changed = _changed(preset)
    assert set(changed) <= KNOBS, f"{preset} changes undocumented keys {set(changed) - KNOBS}"
    if preset == "balanced":
        assert changed == {}, "balanced is the default config"
    else:
        assert changed, f"{preset} changes nothing"


def _decoder_convs(model) -> int:
    return sum(isinstance(m, torch.nn.Conv2d) for m in model.decoder.stages[0].modules())


@pytest.mark.parametrize("preset", PRESETS)
def test_preset_builds_a_model_of_its_sizes(preset):
    cfg = _cfg([f"+preset={preset}"])
    m = cfg.model
    model = build_model(OmegaConf.to_container(m, resolve=True))
    convs = [c for c in model.encoder.backbone.modules() if isinstance(c, torch.nn.Conv2d)]
    assert [c.out_channels for c in convs[::2]] == list(m.encoder.widths)
    assert model.decoder.out.in_channels == m.decoder.widths[-1]
    assert _decoder_convs(model) == m.decoder.convs
    assert model.decoder.grid * 2 ** len(m.decoder.widths) == m.crop_size
    assert model.detector.num_windows == m.num_windows
    # a window crop of the preset's size goes through encoder and decoder
    app, latent = model.encoder(torch.rand(2, 3, m.crop_size, m.crop_size))
    rgb, logit = model.decoder(latent, app)
    assert rgb.shape == (2, 3, m.crop_size, m.crop_size) and torch.isfinite(logit).all()


def _window_flops(preset: str) -> int:
    m = _cfg([f"+preset={preset}"]).model
    model = build_model(OmegaConf.to_container(m, resolve=True))
    with FlopCounterMode(display=False) as fc, torch.no_grad():
        app, latent = model.encoder(torch.rand(1, 3, m.crop_size, m.crop_size))
        model.decoder(latent, app)
    return fc.get_total_flops()


def test_presets_are_ordered_by_cost():
    fast, balanced, accurate = (_window_flops(p) for p in PRESETS)
    assert fast < balanced < accurate


def test_preset_selectable_on_the_command_line():
    out = subprocess.run(
        [sys.executable, "-m", "nsd.cli.train", "+preset=fast", "--cfg", "job"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    job = OmegaConf.create(out.stdout)
    assert job.model.crop_size == _cfg(["+preset=fast"]).model.crop_size


def test_unknown_preset_is_a_clear_error():
    with pytest.raises(Exception, match="preset"):
        _cfg(["+preset=turbo"])
