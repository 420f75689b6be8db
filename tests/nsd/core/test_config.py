"""One source of defaults (nsd/core/config.py): the shipped YAML, for Python and the CLI alike."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml
from omegaconf import OmegaConf

from netepu.geometry.data import DataConfig
from netepu.geometry.losses import GeometryLossWeights
from netepu.geometry.maps import MapSettings
from netepu.geometry.stage import GeometryStageConfig
from netepu.texture.config import TextureConfig
from netepu.texture.data import TextureDataConfig
from netepu.texture.stage import TextureStageConfig
from nsd.core.config import ConfigSection, compose_app
from nsd.core.errors import ConfigError
from nsd.core.trainer import TrainerConfig
from nsd.inference.multiview import InferenceSettings
from nsd.model.bi_nvs import BiNVSConfig
from nsd.model.build import build_model
from nsd.training.task import AdamConfig

ROOT = Path(__file__).resolve().parents[3]

# the command line of each app (python -m MODULE)
CLI = {
    "train": "nsd.cli.train",
    "eval": "nsd.cli.evaluate",
    "export": "nsd.cli.export",
    "run": "netepu.pipeline.run",
    "synth": "nsd.synth.cli",
    "netepu_train": "netepu.cli.train",
    "netepu_embed": "netepu.pipeline.embed",
    "check": "nsd.cli.check",
    "calib": "nsd.cli.calib",
}
SECTIONS = [
    BiNVSConfig,
    TrainerConfig,
    InferenceSettings,
    TextureConfig,
    TextureStageConfig,
    MapSettings,
    GeometryLossWeights,
    DataConfig,
    TextureDataConfig,
    AdamConfig,
]


@pytest.fixture(scope="module")
def cli_configs() -> dict[str, dict]:
    """Each app's job config as its command line prints it (``--cfg job``)."""
    out = {}
    for app, module in CLI.items():
        res = subprocess.run(
            [sys.executable, "-m", module, "--cfg", "job"],
            capture_output=True,
            text=True,
            cwd=ROOT,
            timeout=120,
        )
        assert res.returncode == 0, f"{module}: {res.stderr[-2000:]}"
        out[app] = yaml.safe_load(res.stdout)
    return out


APPS = sorted(p.stem for p in (ROOT / "conf").glob("*.yaml"))


def test_every_app_has_a_command_line():
    assert set(CLI) == set(APPS)
    with pytest.raises(ConfigError, match="no app config 'nope'"):
        compose_app("nope")


@pytest.mark.parametrize("app", APPS)
def test_python_composes_what_the_command_line_runs(app, cli_configs):
    py = OmegaConf.to_container(compose_app(app), resolve=False)
    py.pop("hydra", None)
    assert py == cli_configs[app]


@pytest.mark.parametrize("section", [*SECTIONS, GeometryStageConfig], ids=lambda c: c.__name__)
def test_settings_have_no_defaults_of_their_own(section):
    """Every field's default comes from the YAML: the dataclass has none to disagree with."""
    own = [
        f.name
        for f in dataclasses.fields(section)
        if f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING
    ]
    assert own == []


@pytest.mark.parametrize("section", SECTIONS, ids=lambda c: c.__name__)
def test_python_defaults_are_the_command_lines(section, cli_configs):
    node = OmegaConf.select(OmegaConf.create(cli_configs[section.APP]), section.KEY)
    assert node is not None, f"{section.APP} has no {section.KEY}"
    from_cli = section.from_config(OmegaConf.to_container(node, resolve=True))
    assert section.defaults() == from_cli


def test_geometry_stage_defaults_are_its_three_sections(cli_configs):
    net = cli_configs["netepu_train"]["netepu"]
    assert GeometryStageConfig.defaults() == GeometryStageConfig.from_mapping(
        net["optim"], net["points"], net["eval"]
    )
    assert GeometryStageConfig.from_mapping({"batch_size": 3}).near == net["points"]["near"]


def test_python_and_cli_build_the_same_model(cli_configs):
    """The model built from the CLI's model config and from the Python defaults is one model."""
    cli_model = OmegaConf.create(cli_configs["train"]).model
    py_model = compose_app("train").model
    assert cli_model.num_windows == py_model.num_windows == "auto"  # settled for a scene
    cli_model.num_windows = py_model.num_windows = 2
    torch.manual_seed(0)
    a = build_model(OmegaConf.to_container(cli_model, resolve=True))
    torch.manual_seed(0)
    b = build_model(OmegaConf.to_container(py_model, resolve=True))
    assert a.cfg == b.cfg == BiNVSConfig.defaults(num_windows=2)
    sa, sb = a.state_dict(), b.state_dict()
    assert sa.keys() == sb.keys()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)


def test_training_modes_the_experiments_choose():
    """The default trains the auto-encoder (docs/nsd.md "Which view to re-synthesise");
    experiment=bi_nvs and the paper as written train Bi-NVS across views."""
    assert compose_app("train").model.mode == "autoencoder"
    assert compose_app("train", ["experiment=bi_nvs"]).model.mode == "bi_nvs"
    assert compose_app("train", ["experiment=paper"]).model.mode == "bi_nvs"
    assert compose_app("train", ["experiment=no_depth"]).model.mode == "autoencoder"


def test_overrides_and_bad_keys_name_the_key():
    assert BiNVSConfig.defaults(crop_size=48).crop_size == 48
    assert TrainerConfig.defaults(max_steps=7).max_steps == 7
    with pytest.raises(ConfigError, match=r"model: unknown keys \['crop_sise'\]"):
        BiNVSConfig.defaults(crop_sise=48)
    full = BiNVSConfig.default_mapping()
    del full["mask_floor"]
    with pytest.raises(ConfigError, match=r"model: missing keys \['mask_floor'\]"):
        BiNVSConfig.from_config(full)
    for bad in (0, "some", True, 2.5):
        with pytest.raises(ConfigError, match=r"model\.num_windows must be auto or an integer"):
            BiNVSConfig.defaults(num_windows=bad)
    assert BiNVSConfig.defaults().num_windows == "auto"
    with pytest.raises(ConfigError, match=r"num_windows=auto is chosen for a scene"):
        build_model(OmegaConf.to_container(compose_app("train").model, resolve=True))


def test_default_mapping_is_a_fresh_copy():
    a = TextureConfig.default_mapping()
    a["widths"].append(999)
    assert 999 not in TextureConfig.default_mapping()["widths"]


def test_a_subclass_without_yaml_is_a_clear_error():
    @dataclasses.dataclass
    class Nowhere(ConfigSection):
        APP = "train"
        KEY = "no_such_section"
        x: int

    with pytest.raises(ConfigError, match="no section 'no_such_section'"):
        Nowhere.defaults()


def test_synthetic_world_defaults_are_the_yaml():
    """A scene config takes conf/synth.yaml's values for every key it lacks; the default
    scene (``default_config``) is the YAML as shipped, and the nested settings' own
    defaults (used where no scene is involved, e.g. the renderer's default light) agree."""
    from nsd.synth.backdrop import Backdrop
    from nsd.synth.config import PreviewConfig, SceneConfig, shipped_scene_values
    from nsd.synth.motion import MotionConfig
    from nsd.synth.scene import default_config
    from nsd.synth.shading import Light

    own = [f.name for f in dataclasses.fields(SceneConfig) if f.default is not dataclasses.MISSING
           or f.default_factory is not dataclasses.MISSING]  # fmt: skip
    assert own == []
    assert SceneConfig.from_dict({}) == default_config()
    shipped = shipped_scene_values()
    partial = SceneConfig.from_dict({"motion": {"area_radius": 0.9}})
    assert partial.motion.area_radius == 0.9
    assert partial.motion.interaction == shipped["motion"]["interaction"]
    assert default_config().motion == MotionConfig.defaults()
    for key, cls in (("backdrop", Backdrop), ("light", Light), ("preview", PreviewConfig)):
        assert getattr(default_config(), key) == cls(), key
