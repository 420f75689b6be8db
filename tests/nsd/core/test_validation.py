"""Every config value is checked before any work (nsd/core/validation.py)."""

from __future__ import annotations

from importlib.resources import files

import pytest

from nsd.core.config import compose_app
from nsd.core.errors import ConfigError
from nsd.core.validation import DEVICE, RULES, Rule, check_config, leaves

APPS = ["train", "run", "eval", "export", "synth", "netepu_train", "netepu_embed", "check",
        "calib"]


def _group_options() -> list[tuple[str, str]]:
    """(group, option) of every option file of nsd-train's groups."""
    conf = files("nsd.conf")
    out = []
    for group in conf.iterdir():
        if group.is_dir() and group.name not in ("hydra", "netepu", "__pycache__"):
            out += [(group.name, f.name[:-5]) for f in group.iterdir() if f.name.endswith(".yaml")]
    return sorted(out)


@pytest.mark.parametrize("app", APPS)
def test_every_shipped_default_passes(app):
    check_config(app, compose_app(app))


@pytest.mark.parametrize(("group", "option"), _group_options())
def test_every_shipped_group_option_passes(group, option):
    """The shipped options (priors, experiments, presets) are valid configs themselves."""
    sign = "+" if group in ("preset",) else ""
    overrides = [f"{sign}{group}={option}"]
    check_config("train", compose_app("train", overrides), overrides)


@pytest.mark.parametrize(
    ("app", "override", "message"),
    [
        ("train", "trainer.max_steps=abc", "trainer.max_steps = 'abc': must be an integer"),
        ("train", "batch_size=-1", "batch_size = -1: must be an integer >= 1"),
        ("train", "prior_position.weight=-0.5", "prior_position.weight = -0.5: must be a finite"),
        ("train", "loss.ssim_weight=inf", "loss.ssim_weight = inf"),
        ("train", "optim.lr_decoder=nan", "optim.lr_decoder = nan: must be a finite number > 0"),
        ("train", "data.image_size=[0,0]", "data.image_size = [0, 0]: must be a list of 2"),
        ("train", "data.image_size=[64]", "data.image_size = [64]"),
        ("train", "model.mode=foo", "model.mode = 'foo': must be one of bi_nvs, autoencoder"),
        ("train", "trainer.resume=maybe", "trainer.resume = 'maybe': must be true or false"),
        ("train", "loss.ssim_window=6", "loss.ssim_window = 6: must be an integer >= 3, odd"),
        ("run", "threads=-2", "threads = -2: must be an integer >= 0"),
        ("run", "device=gpu", "device = 'gpu': must be one of auto, cpu, cuda, cuda:N, mps"),
        ("netepu_embed", "device=cuda0", "device = 'cuda0': must be one of auto, cpu, cuda"),
        ("run", "train.model.crop_size=2", "train.model.crop_size = 2"),
        ("run", "+export.batch_size=0", "export.batch_size = 0"),
        ("run", "+export.nonsense=1", "export.nonsense: nsd-export has no such key"),
        ("export", "tracking.max_tracks=0", "tracking.max_tracks = 0: must be an integer >= 1"),
        ("export", "tracking.max_tracks=some", "tracking.max_tracks = 'some'"),
        ("run", "train.prior_mask=hull",
         "train.prior_mask is a group of settings, not one value; choose its option with "
         "prior_mask@train.prior_mask=hull"),
        ("run", "netepu.keypoints.point_budget=-1",
         "netepu.keypoints.point_budget = -1: must be an integer >= 0"),
        ("eval", "max_frames=-3", "max_frames = -3"),
        ("synth", "num_individuals=9", "num_individuals = 9: must be an integer >= 1 and <= 8"),
        ("netepu_train", "netepu.optim.lr=0", "netepu.optim.lr = 0: must be a finite number > 0"),
        ("netepu_train", "netepu.texture.model.crop_margin=-1",
         "netepu.texture.model.crop_margin = -1: must be a finite number >= 0"),
    ],
)
def test_a_bad_value_is_named_with_its_range(app, override, message):
    with pytest.raises(ConfigError) as e:
        check_config(app, compose_app(app, [override]), [override])
    assert message in str(e.value)


@pytest.mark.parametrize(("app", "overrides"), [
    ("run", ["prior_mask@train.prior_mask=hull"]), ("run", ["train.prior_mask.weight=2.0"]),
    ("train", ["prior_mask=hull"]), ("run", ["netepu.keypoints.point_budget=0"]),
    ("netepu_train", ["netepu.texture.model.crop_margin=null"]),
    ("export", ["tracking.max_tracks=null"]), ("export", ["tracking.max_tracks=4"])])
def test_a_group_chosen_the_right_way_passes(app, overrides):
    check_config(app, compose_app(app, overrides), overrides)  # no ConfigError


def test_group_choice_selects_the_defaults_that_are_checked():
    """prior_presence=hull brings count_window (odd): an even value is refused."""
    ov = ["prior_presence=hull", "prior_presence.count_window=4"]
    with pytest.raises(ConfigError, match=r"prior_presence\.count_window = 4"):
        check_config("train", compose_app("train", ov), ov)


def test_min_scale_above_max_scale_is_refused():
    ov = ["model.detector.min_scale=0.9", "model.detector.max_scale=0.5"]
    with pytest.raises(ConfigError, match=r"min_scale = 0\.9 is above"):
        check_config("train", compose_app("train", ov), ov)


@pytest.mark.parametrize(
    ("rule", "good", "bad"),
    [
        (Rule("int", low=1), [1, 7], [0, 1.5, True, "1", None]),
        (Rule("number", above=0), [1e-9, 3], [0, -1, float("nan"), float("inf"), False]),
        (Rule("int", low=1, odd=True), [1, 3], [2, 4]),
        (Rule("str", choices=("a", "b")), ["a"], ["c", 1]),
        (Rule("ints", low=1, length=2), [[1, 2]], [[1], [0, 1], [1.5, 2], "12"]),
        (Rule("bool", allow=("auto",)), [True, "auto"], ["yes", 1]),
        (Rule("str", null=True), [None, "x"], [3]),
        (DEVICE, ["auto", "cpu", "cuda", "cuda:0", "cuda:12", "mps"],
         ["gpu", "cuda:", "cuda:a", "CUDA", " cpu", 0, None]),
    ],
)
def test_rules_accept_and_refuse(rule, good, bad):
    assert all(rule.ok(v) for v in good)
    assert not any(rule.ok(v) for v in bad)


def test_every_rule_names_a_key_that_exists():
    """A rule for a key no config has would be a typo that checks nothing."""
    known: set[str] = set()
    for app in APPS:
        known |= {p for p, _ in leaves(compose_app(app))}
    for group, option in _group_options():
        known |= {p for p, _ in leaves(compose_app("train", [f"+{group}={option}"]
                                                   if group == "preset" else
                                                   [f"{group}={option}"]))}
    known |= {p.split(".", 1)[1] for p in known if "." in p}  # paths inside a group
    for table, rules in RULES.items():
        for key in rules:
            assert key in known, f"RULES[{table!r}][{key!r}] names no config key"


def test_background_rule_lists_every_method():
    from nsd.cues.background import BACKGROUND_METHODS

    assert RULES["data"]["background"].choices == BACKGROUND_METHODS


def test_species_rule_lists_every_choice():
    from netepu.pipeline.species_models import SPECIES

    assert RULES["run"]["netepu.species"].choices == SPECIES
