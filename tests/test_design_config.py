"""`jscratch.design.config` and `jscratch.options`: one declaration per option, from which the
command line is generated; every field has a flag that sets it; configs round-trip through JSON;
bad values are refused with one-line `InputError`s naming the field."""

import dataclasses
import os
import math
import json
import typing

import numpy as np
import pytest

import jscratch
import jscratch.machine
from jscratch import loss as loss_mod
from jscratch import options
from jscratch.errors import InputError
from jscratch.design import cli
from jscratch.design.config import DesignConfig, SceneConfig


def _all_fields(cls, prefix=""):
    """Every (path, field, type) of an option dataclass, nested ones flattened."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        if f.metadata.get("nested"):
            yield from _all_fields(typing.get_args(hints[f.name])[0] if typing.get_args(
                hints[f.name]) else hints[f.name], prefix + f.name + ".")
        else:
            yield prefix + f.name, f, hints[f.name]


def _get(obj, path):
    for part in path.split("."):
        obj = getattr(obj, part)
    return obj


# A value other than the default for every field, as command-line text and as the value the
# config must then hold (fields whose text is not their value's str are listed here).
_SPECIAL = {
    "init_length": (["0.004", "0.02"], (0.004, 0.02)),
    "freeze": (["endpoints,width"], ("endpoints", "width")),
    "targets": (["a.png", "b.png"], ("a.png", "b.png")),
    "loss.vgg_weights": (["w.npz"], "w.npz"),
    "target_ssim": (["0.5"], 0.5),
    "views": (["2"], 2),  # with two targets
    "camera_theta_deg": (["40"], 40.0),
    "offset_deg": (["10"], 10.0),
    "loss.lambda_g": (["3"], 3.0),
    "coordinator": (["localhost:1234"], "localhost:1234"),
    "num_processes": (["2"], 2),
    "process_id": (["1"], 1),
    "config": None,  # covered by the --config tests
    "resume": None,  # covered by the resume tests
}


def _other_value(path, f, tp, default):
    if path in _SPECIAL:
        return _SPECIAL[path]
    choices = f.metadata.get("choices")
    if choices:
        other = next(c for c in choices if c != default)
        return [other], other
    if tp is bool:
        return None  # flag form below
    if tp is int:
        return [str(default + 1)], default + 1
    if tp is float:
        v = 0.5 * default if default else 0.25
        return [repr(v)], v
    if tp is str:
        return ["somewhere"], "somewhere"
    raise AssertionError(f"no test value for {path} ({tp})")


def test_every_field_has_a_flag_that_sets_it(tmp_path):
    """For every field of RunOptions, SceneConfig, DesignConfig and its LossConfig: the generated
    flag exists and sets exactly that field (the others keep their defaults)."""
    machine = tmp_path / "m.toml"
    prof = jscratch.machine.MachineProfile.from_dict({}, name="other")
    machine.write_text(prof.to_toml())
    covered = set()
    for cls, index in ((cli.RunOptions, 0), (SceneConfig, 1), (DesignConfig, 2)):
        flag_of = options.flags(cls)
        defaults = cls()
        for path, f, tp in _all_fields(cls):
            assert path in flag_of or not f.metadata.get("cli", True), path
            flag = flag_of[path]
            default = _get(defaults, path)
            if path == "machine":
                argv, want = [flag, str(machine)], prof.to_dict()
            else:
                other = _other_value(path, f, tp, default)
                if other is None and path in _SPECIAL:
                    continue
                if other is None:  # a bool: --x / --no-x
                    argv = [flag if not default else "--no-" + flag[2:]]
                    want = not default
                else:
                    text, want = other
                    argv = text if flag == "targets" else [flag, *text]
            if path == "views":
                argv = ["a.png", "b.png", *argv]
            if path == "loss.vgg_weights":
                argv += ["--lambda-g", "1"]
            got = cli.configs(argv)[index]
            if path == "targets":  # (held as absolute paths)
                want = tuple(os.path.abspath(t) for t in want)
            assert _get(got, path) == want, (path, argv)
            covered.add(path)
    assert {"n_scratches", "seed", "dtype", "loss.lambda_x", "targets", "out"} <= covered


def test_flags_are_unique_and_docs_complete():
    seen = {}
    for cls in (cli.RunOptions, SceneConfig, DesignConfig):
        for path, flag in options.flags(cls).items():
            assert flag not in seen, (flag, path, seen.get(flag))
            seen[flag] = path
    for cls in (cli.RunOptions, SceneConfig, DesignConfig, loss_mod.LossConfig):
        for f in dataclasses.fields(cls):
            assert f.metadata.get("help"), f"{cls.__name__}.{f.name} has no help"


def test_help_shows_each_default_once(capsys):
    with pytest.raises(SystemExit) as e:
        cli.parser().parse_args(["--help"])
    assert e.value.code == 0
    text = capsys.readouterr().out
    for block in text.split("\n  --")[1:]:
        assert block.count("(default") <= 1, block


def test_defaults_are_one_truth():
    """The command line with no options asks for exactly the library's defaults."""
    run, scene, config = cli.configs([])
    assert config == DesignConfig()
    assert scene == SceneConfig()
    assert config.loss == loss_mod.LossConfig()
    assert config.groove == "carvable" and config.loss.lambda_x == loss_mod.LAMBDA_X
    assert config.machine == jscratch.machine.MachineProfile.from_dict({}).to_dict()


def test_config_json_round_trip():
    cfg = DesignConfig(n_scratches=123, freeze=("width", "alpha"), init_length=(0.001, 0.002),
                       loss=loss_mod.LossConfig(kind="perceptual", lambda_x=0.0),
                       target_ssim=0.7)
    back = DesignConfig.from_dict(json.loads(json.dumps(cfg.to_dict())))
    assert back == cfg
    scene = SceneConfig(targets=("x.png",), theta_deg=40.0)
    assert SceneConfig.from_dict(json.loads(json.dumps(scene.to_dict()))) == scene


@pytest.mark.parametrize("kw, field", [
    ({"iterations": 0}, "iterations"),
    ({"n_scratches": -1}, "n_scratches"),
    ({"n_scratches": 2.5}, "n_scratches"),
    ({"init_width": float("nan")}, "init_width"),
    ({"lr_width": "fast"}, "lr_width"),
    ({"groove": "deep"}, "groove"),
    ({"freeze": ("legs",)}, "freeze"),
    ({"prune_fraction": 1.5}, "prune_fraction"),
    ({"target_ssim": 0.0}, "target_ssim"),
    ({"adam_b2": 1.0}, "adam_b2"),
    ({"cull_eps": 1.0}, "cull_eps"),
    ({"coverage_eps": 2.0}, "coverage_eps"),
    ({"cull_eps": -1e-3}, "cull_eps"),
    ({"machine": {"cutter_radius_mm": -1}}, "cutter_radius_mm"),
    ({"seed": 2**63}, r"seed must be an int in \[0, 2\*\*63\)"),  # beyond jax's PRNG seed
    ({"freeze": None}, "freeze"),
    ({"freeze": 5}, "freeze"),
    ({"freeze": {"alpha": 1}}, "freeze"),
    ({"discard": "no"}, "discard must be true or false"),
    ({"adam_eps": 0.0}, "adam_eps must be finite and > 0"),  # 0/0 in a frozen group
    ({"machine": "foo"}, "machine must be None or a machine profile"),
    ({"loss": {"vgg_weights": 5, "lambda_g": 1.0}}, "vgg_weights must be None or a file path"),
    ({"init_length": 5}, "init_length"),
])
def test_bad_design_config_is_one_line_input_error(kw, field):
    with pytest.raises(InputError, match=field) as e:
        DesignConfig(**kw)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("d, what", [
    ({"n_scratchez": 5}, "unknown fields"),
    ({"loss": {"lambda_q": 1}}, "unknown fields"),
    ([], "JSON object"),
    ({"init_length": 5}, "init_length must be"),
    ({"freeze": 5}, "freeze must be"),
    ({"machine": "foo"}, "machine must be"),
])
def test_bad_config_dict(d, what):
    with pytest.raises(InputError, match=what):
        DesignConfig.from_dict(d)


@pytest.mark.parametrize("kw, field", [
    ({"size": 8}, "size"),
    ({"theta_deg": 95.0}, "theta_deg"),
    ({"targets": ("a.png",), "views": 2}, "target images for 2 views"),
    ({"board": -0.3}, "board"),
    ({"targets": None}, "targets must be a list"),
    ({"targets": 5}, "targets must be a list"),
    ({"theta_deg": True}, "theta_deg must be a finite number"),
])
def test_bad_scene_config(kw, field):
    with pytest.raises(InputError, match=field):
        SceneConfig(**kw)


def test_numpy_numbers_in_a_scene_are_plain_json():
    """numpy scalars are taken as the numbers they hold, so a saved config is plain JSON."""
    sc = SceneConfig(size=np.int64(32), views=np.int64(2), theta_deg=np.float32(40.0))
    assert json.loads(json.dumps(sc.to_dict())) == sc.to_dict()
    assert (sc.size, sc.views, sc.theta_deg) == (32, 2, 40.0)


def test_scene_views_match_views_on_circle():
    """Degrees in the scene config, radians in `views_on_circle`: the same views."""
    import math

    import numpy as np

    scene = SceneConfig(theta_deg=40.0, offset_deg=30.0, views=4, size=32)
    board = scene.make_board()
    want = jscratch.views_on_circle(4, math.radians(40.0), 1.0, math.radians(30.0), board)
    got = scene.make_views()
    np.testing.assert_array_equal(np.asarray(got.camera), np.asarray(want.camera))
    np.testing.assert_array_equal(np.asarray(got.light), np.asarray(want.light))
    default = jscratch.views_on_circle(3, board=board)  # the default polar angle is 50 degrees
    np.testing.assert_array_equal(np.asarray(SceneConfig(size=32).make_views().camera),
                                  np.asarray(default.camera))


def test_dense_design_weighs_the_gram_term_by_dense_lambda_g():
    """From ``dense_from`` scratches per pixel on, the design's loss takes ``dense_lambda_g`` for
    ``E_g`` unless ``lambda_g`` is given; below it, or with a given weight, the loss is unchanged."""

    px = 256 * 256
    assert DesignConfig().design_loss(px) == DesignConfig().loss  # 20,000: 0.31 per pixel
    assert not DesignConfig().is_dense(px)
    dense = DesignConfig(n_scratches=60_000)
    assert dense.is_dense(px) and dense.design_loss(px).lambda_g == 60.0
    assert loss_mod.make_loss(dense.design_loss(px)).lambda_g == 60.0
    at = DesignConfig(n_scratches=math.ceil(0.4 * px))
    assert at.is_dense(px) and not DesignConfig(n_scratches=at.n_scratches - 1).is_dense(px)
    given = DesignConfig(n_scratches=60_000, loss={"lambda_g": 200.0})
    assert given.design_loss(px).lambda_g == 200.0
    never = DesignConfig(n_scratches=60_000, dense_from=0.0)
    assert not never.is_dense(px) and never.design_loss(px).lambda_g is None
    assert DesignConfig(n_scratches=60_000, loss={"kind": "perceptual"}).design_loss(px) == \
        DesignConfig(loss={"kind": "perceptual"}).loss


def test_an_unknown_keyword_is_refused_in_one_line_as_an_unknown_key():
    """`DesignConfig`, `SceneConfig` and `LossConfig` called with a keyword that names no field
    (a typo) refuse it as their ``from_dict`` refuses an unknown key: a one-line jscratch error
    naming it, not Python's TypeError; copies, replacements and pickles still work."""
    import copy
    import pickle

    from jscratch.designfile import DesignError
    from jscratch.errors import InputError
    from jscratch.loss import LossConfig

    for make, cls, err in ((lambda: DesignConfig(n_scratch=10), "DesignConfig", DesignError),
                           (lambda: SceneConfig(sise=32), "SceneConfig", DesignError),
                           (lambda: LossConfig(lamda_x=0.0), "LossConfig", InputError)):
        with pytest.raises(err, match=rf"^{cls}: unknown fields \['\w+'\] \(known: ") as e:
            make()
        assert "\n" not in str(e.value)
    with pytest.raises(DesignError, match=r"^DesignConfig.loss: unknown fields \['kindd'\]$"):
        DesignConfig(loss={"kindd": "l2"})
    c = DesignConfig(n_scratches=10, loss={"lambda_x": 0.0})
    assert dataclasses.replace(c, iterations=3).iterations == 3
    assert copy.deepcopy(c) == c == pickle.loads(pickle.dumps(c)) == DesignConfig.from_dict(
        c.to_dict())


def test_scratch_count_and_image_side_are_bounded_by_their_32_bit_indices():
    from jscratch.designfile import DesignError

    assert DesignConfig(n_scratches=2**31 - 1).n_scratches == 2**31 - 1
    with pytest.raises(DesignError, match=r"n_scratches must be an int in \[1, 2147483647\]"):
        DesignConfig(n_scratches=2**31)
    assert SceneConfig(size=46340).size == 46340 and 46340**2 < 2**31 <= 46341**2
    with pytest.raises(DesignError, match=r"size must be an int in \[16, 46340\]"):
        SceneConfig(size=46341)
