"""The declarative config schema (issue 27, item 1): every key described, errors in the project's style, the JSON
Schema export (`adseismic schema`), docs/config.md generated from it and the `adseismic init` templates."""
import dataclasses
import importlib.util
import json
from pathlib import Path

import pytest
import yaml

from adseismic import cli
from adseismic.config import ConfigError, InversionConfig, SimulationConfig, parse_config, parse_fwi_config, schema
from adseismic.config.schema import SCHEMAS, validate_section

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
EXAMPLES = {"forward": ["example_2d", "example_3d", "marmousi_forward", "elastic_forward", "das_forward",
                        "acoustic_vd_forward", "vti_forward", "viscoacoustic_forward"],
            "fwi": ["fwi_demo", "marmousi_fwi", "elastic_fwi", "nn_fwi"], "locate": ["locate_demo", "locate_mt_demo"],
            "image": ["image_marmousi", "image_elastic"]}


def sections(cls, seen=None):
    """Every schema model reachable from ``cls``."""
    seen = {} if seen is None else seen
    seen[cls.__name__] = cls
    for name in cls.model_fields:
        sub = schema._section_of(cls, [name])
        if sub is not None and sub.__name__ not in seen:
            sections(sub, seen)
    return seen


# ------------------------------------------------------------------------------ the schema describes every key

@pytest.mark.parametrize("workflow", list(SCHEMAS))
def test_every_key_has_a_meaning_and_a_documented_unit(workflow):
    for sec in sections(SCHEMAS[workflow]).values():
        assert sec.__doc__ and sec.model_config.get("extra") == "forbid", sec
        for name, field in sec.model_fields.items():
            assert field.description and len(field.description) > 5, f"{sec.__name__}.{name}"
    props = schema.json_schema(workflow)["$defs"]["Simulation"]["properties"]
    assert props["dt"]["unit"] == "s" and props["dt"]["description"].startswith("time step")
    assert props["order"]["default"] == 4


def test_schema_keys_are_the_dataclass_fields_and_the_parsers_keys():
    from adseismic.config import forward, fwi, locate

    assert list(schema.Simulation.model_fields) == [f.name for f in dataclasses.fields(SimulationConfig)]
    assert set(schema.Inversion.model_fields) == {f.name for f in dataclasses.fields(InversionConfig)}
    assert set(schema.Inversion.model_fields) == set(fwi.INVERSION_KEYS)
    assert set(schema.Observed.model_fields) == set(fwi.OBSERVED_KEYS)
    assert set(schema.ForwardSchema.model_fields) == set(forward.SECTIONS)
    assert set(schema.FWISchema.model_fields) == set(forward.SECTIONS) | set(fwi.FWI_SECTIONS)
    assert set(schema.LocateSchema.model_fields) == set(locate.LOCATE_SECTIONS)
    assert schema.MISFIT_NAMES == fwi.MISFIT_NAMES and schema.LOCATE_METHODS == locate.LOCATE_METHODS
    from adseismic.config.parallel import PARALLEL_KEYS

    assert tuple(schema.Parallel.model_fields) == PARALLEL_KEYS
    from adseismic.data import models

    kinds = set(models._GENERATOR_KEYS) | set(models._FILE_KEYS)
    keys = models._COMMON_KEYS | {"shape", "spacing", "path", "units", "axes"}
    keys |= set().union(*models._GENERATOR_KEYS.values(), *models._FILE_KEYS.values())
    assert set(schema.ModelSpec.model_fields) == keys
    assert set(schema.ModelSpec.model_fields["kind"].annotation.__args__) == kinds


@pytest.mark.parametrize("workflow, name", [(w, n) for w, names in EXAMPLES.items() for n in names])
def test_shipped_configs_fit_the_schema_and_its_json_export(workflow, name):
    raw = yaml.safe_load((CONFIGS / f"{name}.yaml").read_text())
    SCHEMAS[workflow].model_validate(raw)  # the whole file, model spec included
    jsonschema = pytest.importorskip("jsonschema")
    jsonschema.validate(json.loads(json.dumps(raw, default=str)), schema.json_schema(workflow))


# ------------------------------------------------------------------------------ error messages

@pytest.mark.parametrize("cls, raw, key, start, fragment", [
    (schema.Simulation, {"oder": 4}, "simulation", "simulation.oder: unknown key", "allowed: order, accuracy"),
    (schema.Simulation, [1], "simulation", "simulation: [1] is not a mapping", "simulation: {...}"),
    (schema.Simulation, {"dt": True}, "simulation", "simulation.dt: True", "true/false are not numbers"),
    (schema.Simulation, {"dx": -1}, "simulation", "simulation.dx: -1 is not > 0", "metres"),
    (schema.Inversion, {"bands": [3, {"fmin": "x"}]}, "inversion", "inversion.bands[1].fmin: 'x'", "Hz"),
    (schema.Inversion, {"bands": [3, {"fmax": 5, "lo": 1}]}, "inversion", "inversion.bands[1].lo: unknown key",
     "allowed: fmin, fmax"),
    (schema.Inversion, {"iterations": [3, "many"]}, "inversion", "inversion.iterations[1]: 'many'", "whole number"),
    (schema.Inversion, {"bounds": [1, "fast"]}, "inversion", "inversion.bounds[1]: 'fast'", "m/s"),
    (schema.Inversion, {"misfit": "l3"}, "inversion", "inversion.misfit: 'l3' is not one of", "envelope"),
    (schema.Preprocess, {}, "preprocess", "preprocess.noise_window: missing", "before the first arrival"),
    (schema.Search, {"iterations": 0}, "search", "search.iterations: 0 < 1", "at least 1"),
])
def test_schema_errors_name_the_key_the_value_and_the_fix(cls, raw, key, start, fragment):
    with pytest.raises(ConfigError) as e:
        validate_section(cls, raw, key)
    assert str(e.value).startswith(start) and fragment in str(e.value), str(e.value)


def test_validated_values_reach_the_dataclasses():
    raw = yaml.safe_load((CONFIGS / "fwi_demo.yaml").read_text())
    raw["simulation"] = {"dt": "1e-3", "pml_width": 12.0, "free_surface": None}
    raw["inversion"].update({"bands": [2, {"fmin": 1, "fmax": 4}, None], "iterations": [1, 2, 3], "bounds": [1500, 3000]})
    c = parse_fwi_config(raw, base_dir=CONFIGS)
    assert c.forward.simulation.dt == 1e-3 and c.forward.simulation.pml_width == 12
    assert c.forward.simulation.free_surface is False  # null: the default
    assert c.inversion.bands == [(None, 2.0), (1.0, 4.0), (None, None)]
    assert c.inversion.iterations == [1, 2, 3] and c.inversion.bounds == (1500.0, 3000.0)
    raw["inversion"]["bands"] = [{"fmin": 4, "fmax": 2}]  # cross-key rules stay in the parser
    with pytest.raises(ConfigError, match=r"^inversion.bands\[0\]: fmin 4 Hz >= fmax 2 Hz"):
        parse_fwi_config(raw, base_dir=CONFIGS)
    with pytest.raises(ConfigError, match=r"^wavelet.delay: 50 s is more than 100 periods"):
        parse_config({**raw, "wavelet": {"kind": "ricker", "peak_frequency": 10, "delay": 50}}, base_dir=CONFIGS,
                     extra_sections=("true_model", "inversion"))


# ------------------------------------------------------------------------------ adseismic schema, docs/config.md

def test_schema_command_prints_and_writes_the_json_schema(tmp_path, capsys):
    assert cli.main(["schema", "fwi"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["title"] == "adseismic fwi config" and {"inversion", "true_model", "observed"} <= set(printed["properties"])
    assert printed["additionalProperties"] is False
    assert cli.main(["schema", "locate", "-o", str(tmp_path / "locate.json")]) == 0
    written = json.loads((tmp_path / "locate.json").read_text())
    assert written == schema.json_schema("locate") and "traces" in written["required"]


def test_docs_config_md_is_generated_from_the_schema():
    spec = importlib.util.spec_from_file_location("gen_config", ROOT / "docs" / "gen_config.py")
    gen = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gen)
    text = (ROOT / "docs" / "config.md").read_text(encoding="utf-8")
    assert text == gen.render(), "docs/config.md is out of date: run python docs/gen_config.py"
    for workflow, cls in SCHEMAS.items():
        assert f"## `adseismic {workflow}`" in text
        for sec in sections(cls).values():
            for name in sec.model_fields:
                assert f"| `{name}` |" in text
    assert "| `dt` | number | s | null |" in text


# ------------------------------------------------------------------------------ adseismic init

@pytest.mark.parametrize("workflow", list(SCHEMAS))
def test_init_writes_a_commented_template_that_plans(workflow, tmp_path, capsys):
    out = tmp_path / "sub" / f"{workflow}.yaml"
    out.parent.mkdir()
    assert cli.main(["init", workflow, "-o", str(out)]) == 0
    text = out.read_text()
    raw = yaml.safe_load(text)
    SCHEMAS[workflow].model_validate(raw)
    for line in text.splitlines():  # every key carries its meaning
        if line.strip() and not line.lstrip().startswith("#"):
            assert " # " in line, line
    assert "yaml-language-server: $schema=" in text
    assert cli.main(["init", workflow, "-o", str(out)]) == 2  # never overwrites
    assert cli.workflow_of(out) == workflow
    capsys.readouterr()
    assert cli.main(["plan", str(out)]) == 0
    plan = capsys.readouterr().out
    assert "dt" in plan and "dx" in plan
    if workflow in ("forward", "fwi"):
        assert cli.main([workflow, str(out), "--dry-run", "-q"]) == 0


def test_init_locate_points_at_the_demo_traces_relative_to_the_file(tmp_path):
    out = tmp_path / "locate.yaml"
    assert cli.main(["init", "locate", "-o", str(out)]) == 0
    raw = yaml.safe_load(out.read_text())
    (mseed,) = raw["traces"]["paths"]
    assert not Path(mseed).is_absolute() and (tmp_path / mseed).resolve() == CONFIGS / "data/location_demo/event.mseed"
    text = schema.template("locate", None)  # an installed package: no demo data next to it
    assert "python -m adseismic.data_synthetic.location data/location_demo" in text
