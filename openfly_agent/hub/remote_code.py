"""`trust_remote_code` support: the two re-export files of a release folder and `auto_map` in config.json."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from openfly_agent.constants import CONFIG_NAME, MODEL_TYPE
from openfly_agent.hub.folder_utils import read_json, write_json

CONFIGURATION_FILE = "configuration_openfly_agent.py"
MODELING_FILE = "modeling_openfly_agent.py"
AUTO_MAP = {
    "AutoConfig": f"{CONFIGURATION_FILE.removesuffix('.py')}.OpenFlyAgentConfig",
    "AutoModel": f"{MODELING_FILE.removesuffix('.py')}.OpenFlyAgent",
}


def write_remote_code(folder: Path, package_version: str) -> list[str]:
    """Write the re-export modules into `folder` (they import the installed package; no second model copy).

    Returns:
        The names of the files written.
    """
    import jinja2

    env = jinja2.Environment(undefined=jinja2.StrictUndefined, keep_trailing_newline=True, autoescape=False)
    templates = resources.files("openfly_agent.hub").joinpath("templates", "remote_code")
    for name in (CONFIGURATION_FILE, MODELING_FILE):
        text = env.from_string(templates.joinpath(f"{name}.j2").read_text())
        (folder / name).write_text(text.render(package_version=package_version))
    return [CONFIGURATION_FILE, MODELING_FILE]


def add_auto_map(folder: Path) -> dict:
    """Set `auto_map` in `folder/config.json` (checking `model_type`) and return the updated config dict."""
    path = folder / CONFIG_NAME
    config = read_json(path)
    if config.get("model_type") != MODEL_TYPE:
        raise ValueError(f"{path}: model_type is {config.get('model_type')!r}, expected {MODEL_TYPE!r}")
    config["auto_map"] = dict(AUTO_MAP)
    write_json(path, config)
    return config
