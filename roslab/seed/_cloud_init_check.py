"""Run by the system python3 with Debian's unpacked cloud-init on its path (roslab.seed.tools).

Reads a JSON mapping of name -> user-data text on stdin; prints a JSON mapping of name ->
list of problems. cloud-init's own schema check (`validate_cloudconfig_schema`, strict),
plus what 22.4's schema lets through: a top-level key no module reads, a document that
is not `#cloud-config`. Imports nothing from roslab (it runs outside roslab's venv).
"""

import json
import sys

import jsonschema  # noqa: F401 - without it cloud-init skips its check silently
import yaml
from cloudinit.config.schema import SchemaValidationError, get_schema, validate_cloudconfig_schema


def known_top_level_keys(schema: dict) -> set:
    keys = set(schema.get("properties", {}))
    definitions = schema.get("$defs", {})
    for part in schema.get("allOf", []):
        reference = part.get("$ref", "")
        if reference.startswith("#/$defs/"):
            keys |= set(definitions.get(reference[len("#/$defs/"):], {}).get("properties", {}))
    return keys


def main() -> int:
    documents = json.load(sys.stdin)
    schema = get_schema()
    known = known_top_level_keys(schema)
    problems = {}
    for name, text in documents.items():
        found = []
        if not text.startswith("#cloud-config\n"):
            found.append("does not start with #cloud-config")
        try:
            config = yaml.safe_load(text)
        except yaml.YAMLError as error:
            problems[name] = [f"not YAML: {getattr(error, 'problem', error)}"]
            continue
        if not isinstance(config, dict):
            problems[name] = ["is not a mapping"]
            continue
        found += [f"{key}: no cloud-init module reads this key" for key in config if key not in known]
        try:
            validate_cloudconfig_schema(config, schema, strict=True, log_details=False)
        except SchemaValidationError as error:
            found += [f"{path}: {message}" for path, message in error.schema_errors or []]
            found += [f"{path}: deprecated: {message}" for path, message in error.schema_deprecations or []]
        problems[name] = found
    json.dump(problems, sys.stdout)
    return 0


if __name__ == "__main__":
    sys.exit(main())
