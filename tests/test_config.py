"""Config loading is strict, overridable from files and the command line, documented, and round-trips."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import yaml

import h2viz.config as config_module
from h2viz.cli import build_config, make_parser
from h2viz.config import (
    CONFIG_DIR,
    SOURCE_CONFIGS,
    Config,
    MappingConfig,
    apply_file,
    apply_overrides,
    dump_config,
    field_docs,
    from_dict,
    load_config,
    mapping_from_dict,
    packaged_config,
    source_config_file,
    to_dict,
)
from h2viz.errors import ConfigError


def test_unknown_key_names_the_key_the_file_and_the_closest_valid_key(tmp_path: Path) -> None:
    f = tmp_path / "bad.yaml"
    f.write_text("mapping:\n  voxel_sise_m: 0.05\n")
    with pytest.raises(ConfigError) as e:
        load_config([f])
    msg = str(e.value)
    assert "voxel_sise_m" in msg and str(f) in msg and "voxel_size_m" in msg


def test_a_misplaced_or_misspelt_key_is_pointed_to_its_group(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="did you mean 'mapping.representation.voxel_size_m'"):
        apply_overrides(Config(), ["mapping.representation.voxel_sise_m=0.05"])
    with pytest.raises(ConfigError, match="did you mean 'mapping.sampling.rays_per_iter'"):
        apply_overrides(Config(), ["mapping.rays_per_iters=1024"])


def test_a_key_repeated_in_one_mapping_is_an_error_naming_the_file_and_the_key(tmp_path: Path) -> None:
    f = tmp_path / "twice.yaml"
    f.write_text("mapping:\n  rendering:\n    color_views: 0\n    render_surface: false\n    color_views: 4\n")
    with pytest.raises(ConfigError, match=r"twice\.yaml: key 'color_views' is repeated \(lines 3 and 5\)"):
        load_config([f])
    f.write_text("mapping:\n  rendering: {color_views: 0}\nsource: {downscale: 2}\n")  # the same name in two mappings
    assert load_config([f]).mapping.rendering.color_views == 0


def test_the_flat_mapping_keys_of_earlier_versions_still_load_with_a_warning_naming_the_new_key(
    tmp_path: Path,
) -> None:
    f = tmp_path / "old.yaml"
    f.write_text("mapping:\n  color_views: 3\n  max_iters: 4\n")
    with pytest.warns(FutureWarning) as seen:
        cfg = load_config([f], ["mapping.rays_per_iter=512"])
    said = [str(w.message) for w in seen]
    assert any(str(f) in m and "mapping.color_views -> mapping.rendering.color_views" in m for m in said)
    assert any("mapping.rays_per_iter -> mapping.sampling.rays_per_iter" in m for m in said)
    assert cfg.mapping.rendering.color_views == 3 and cfg.mapping.optimization.max_iters == 4
    assert cfg.mapping.sampling.rays_per_iter == 512
    with pytest.raises(ConfigError, match="unknown key 'mapping.colour_views'"):
        apply_overrides(Config(), ["mapping.colour_views=3"])  # not a key of either layout


def test_a_checkpoints_mapping_settings_load_in_either_layout() -> None:
    cfg = MappingConfig().updated(voxel_size_m=0.05, max_iters=3, color_views=2)
    assert cfg.representation.voxel_size_m == 0.05 and cfg.optimization.max_iters == 3
    assert mapping_from_dict(to_dict(cfg)) == cfg
    flat = {name: value for group in to_dict(cfg).values() for name, value in group.items()}
    assert mapping_from_dict(flat) == cfg  # written before the groups, read without a warning
    with pytest.raises(TypeError, match="voxel_size_m"):
        cfg.updated(voxel_sise_m=0.05)
    with pytest.raises(AttributeError):
        cfg.max_iters = 5  # type: ignore[attr-defined]  # a flat name would be silently ignored otherwise


def test_unknown_section_and_wrong_types_are_errors(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="did you mean 'mapping'"):
        apply_overrides(Config(), ["maping.max_iters=3"])
    with pytest.raises(ConfigError, match="expected an integer"):
        apply_overrides(Config(), ["mapping.optimization.max_iters=lots"])
    with pytest.raises(ConfigError, match="true/false"):
        apply_overrides(Config(), ["mapping.representation.priors=maybe"])
    f = tmp_path / "list.yaml"
    f.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="top level"):
        load_config([f])
    with pytest.raises(ConfigError, match="section.key=value"):
        apply_overrides(Config(), ["mapping.optimization.max_iters"])


def test_overrides_files_then_command_line(tmp_path: Path) -> None:
    f = tmp_path / "a.yaml"
    mapping = "mapping:\n  optimization: {max_iters: 4}\n  sampling: {rays_per_iter: 1024}\n"
    f.write_text(mapping + "source:\n  synthetic:\n    width: 320\n")
    cfg = load_config(
        [f], ["mapping.optimization.max_iters=7", "source.rosbag.T_body_camera=[1,0,0,0,0,1,0,0,0,0,1,0,0,0,0,1]"]
    )
    assert cfg.mapping.optimization.max_iters == 7 and cfg.mapping.sampling.rays_per_iter == 1024
    assert cfg.source.synthetic.width == 320
    assert len(cfg.source.rosbag.T_body_camera) == 16


def test_every_field_is_documented() -> None:
    def walk(cls: type) -> None:
        docs = field_docs(cls)
        for f in dataclasses.fields(cls):
            assert docs.get(f.name), f"{cls.__name__}.{f.name} has no docstring"
            default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
            if dataclasses.is_dataclass(default):
                walk(type(default))

    walk(Config)


def test_default_yaml_matches_the_dataclass_defaults() -> None:
    data = yaml.safe_load((CONFIG_DIR / "default.yaml").read_text())
    assert data == to_dict(Config()), "regenerate configs/default.yaml from the dataclasses"


def test_every_shipped_config_file_loads() -> None:
    files = sorted((f for f in CONFIG_DIR.iterdir() if f.name.endswith(".yaml")), key=lambda f: f.name)
    assert len(files) >= 7
    for f in files:
        apply_file(Config(), f)


def test_resolved_config_round_trips(tmp_path: Path) -> None:
    cfg = load_config(overrides=["mapping.representation.voxel_size_m=0.2", "viewer.port=9000"])
    dump_config(cfg, tmp_path / "config.yaml")
    again = load_config([tmp_path / "config.yaml"])
    assert again == cfg
    assert from_dict(to_dict(cfg)) == cfg


ROOT = Path(__file__).resolve().parents[1]


def test_the_configs_ship_inside_the_package_and_configs_in_a_clone_is_the_same_folder(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """`configs/` at the root of a clone is what `h2viz/configs` (the packaged files) points at: editing one edits
    the other, and `--config configs/paper.yaml` keeps working from the clone."""
    packaged = Path(str(CONFIG_DIR))
    assert packaged.parent == ROOT / "h2viz" and packaged.resolve() == (ROOT / "configs").resolve()
    for fmt in SOURCE_CONFIGS:
        assert source_config_file(fmt) is not None
    assert source_config_file("auto") is None
    args = make_parser().parse_args(["map", "--config", "configs/paper.yaml", "--data", ""])
    monkeypatch.chdir(ROOT)
    cfg = build_config(args)
    paper = yaml.safe_load((ROOT / "configs" / "paper.yaml").read_text())
    for group, values in paper["mapping"].items():
        for key, value in values.items():
            assert getattr(getattr(cfg.mapping, group), key) == value, f"{group}.{key}"


def test_a_missing_packaged_config_is_an_error_that_says_to_reinstall(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "default.yaml").write_text((Path(str(CONFIG_DIR)) / "default.yaml").read_text())
    monkeypatch.setattr(config_module, "CONFIG_DIR", tmp_path)  # an installation without the per-source files
    load_config()  # the defaults are there
    with pytest.raises(ConfigError, match=r"replica.yaml is missing from .*reinstall h2viz"):
        source_config_file("replica")
    (tmp_path / "default.yaml").unlink()
    with pytest.raises(ConfigError, match=r"default.yaml is missing"):
        load_config()
    with pytest.raises(ConfigError, match=r"paper.yaml is missing"):
        packaged_config("paper")
