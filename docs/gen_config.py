"""Writes docs/config.md from the config schema (adseismic.config.schema): every key of every workflow with its type,
unit, default and meaning. Run `python docs/gen_config.py`; tests/test_schema.py checks that the page is up to date."""
import json
import pathlib

from adseismic.config import schema

PAGE = pathlib.Path(__file__).with_name("config.md")


def _type(prop: dict, defs: dict) -> str:
    """A short type name from a JSON Schema property: number, integer, text, true/false, one of ..., list of ...,
    a section name; ``| null`` is left out (null always means 'not given: the default')."""
    if "$ref" in prop:
        return f"[{prop['$ref'].split('/')[-1]}](#{prop['$ref'].split('/')[-1].lower()})"
    if "enum" in prop:
        return " \\| ".join(f"`{json.dumps(v) if not isinstance(v, str) else v}`" for v in prop["enum"])
    if "const" in prop:
        return f"`{prop['const']}`"
    if "anyOf" in prop:
        parts = [_type(p, defs) for p in prop["anyOf"] if p.get("type") != "null"]
        return " or ".join(dict.fromkeys(parts)) or "null"
    t = prop.get("type")
    if t == "array":
        return f"list of {_type(prop.get('items', {}), defs)}" if prop.get("items") else "list"
    if t == "object":
        extra = prop.get("additionalProperties")
        return f"mapping of {_type(extra, defs)}" if isinstance(extra, dict) and extra else "mapping"
    return {"number": "number", "integer": "integer", "string": "text", "boolean": "true/false",
            None: "any"}.get(t, str(t))


def _default(field) -> str:
    if field.is_required():
        return "**required**"
    d = field.default
    return "null" if d is None else f"`{schema._yaml_value(d)}`"


def _table(cls, defs: dict) -> list[str]:
    props = cls.model_json_schema(ref_template="#/$defs/{model}").get("properties", {})
    out = ["| key | type | unit | default | meaning |", "|---|---|---|---|---|"]
    for name, field in cls.model_fields.items():
        extra = field.json_schema_extra if isinstance(field.json_schema_extra, dict) else {}
        unit = extra.get("unit", "")
        meaning = (field.description or "").replace("|", "\\|")
        out.append(f"| `{name}` | {_type(props.get(name, {}), defs)} | {unit} | {_default(field)} | {meaning} |")
    return out


def render() -> str:
    lines = ["# Config reference", "",
             ("Generated from the schema in `adseismic/config/schema.py` by `python docs/gen_config.py` (do not edit by "
             "hand; tests/test_schema.py checks it is up to date). Every key of each workflow's YAML config: its type, "
             "unit, default and meaning. `null` (or leaving a key out) means the default; number fields also accept "
             "numeric text such as `1e-3`. Unknown keys are errors that name the key and list the allowed ones."), "",
             ("Start from a template (`adseismic init forward|fwi|locate -o FILE`: commented, runs as written); check a "
             "config with `adseismic plan FILE`; for completion in an editor write the JSON Schema with "
             "`adseismic schema fwi -o fwi.schema.json` and put `# yaml-language-server: $schema=fwi.schema.json` at "
             "the top of the config. Cross-key rules (bands low to high, points inside the model, exactly one of "
             "`true_model`/`observed`, ...) are checked when the config is loaded and are named in the meanings."), ""]
    seen = set()
    for workflow, cls in schema.SCHEMAS.items():
        lines += [f"## `adseismic {workflow}`", "", (cls.__doc__ or "").strip().replace("\n    ", " "), ""]
        defs = cls.model_json_schema().get("$defs", {})
        lines += _table(cls, defs) + [""]
        for name in cls.model_fields:
            sub = schema._section_of(cls, [name])
            if sub is None:
                continue
            # sections shared by several workflows are described once, at their first use
            stack = [sub]
            while stack:
                sec = stack.pop(0)
                if sec.__name__ in seen:
                    continue
                seen.add(sec.__name__)
                lines += [f"### {sec.__name__}", "", (sec.__doc__ or "").strip().replace("\n    ", " "), ""]
                lines += _table(sec, defs) + [""]
                for n in sec.model_fields:
                    s2 = schema._section_of(sec, [n])
                    if s2 is not None and s2.__name__ not in seen:
                        stack.append(s2)
    return "\n".join(lines).rstrip() + "\n"


if __name__ == "__main__":
    PAGE.write_text(render(), encoding="utf-8")
    print(f"wrote {PAGE}")
