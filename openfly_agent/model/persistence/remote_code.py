"""`trust_remote_code` files of a checkpoint folder: three re-export modules and the `auto_map` entries.

Every model folder the agent saves (training checkpoints and releases) gets them, so
`AutoModel.from_pretrained(folder, trust_remote_code=True)` and `AutoProcessor.from_pretrained(...)` work on any
of them. The modules import the classes of the installed `openfly-agent` package: no second copy of the model.
"""

from __future__ import annotations

import json
from pathlib import Path

from openfly_agent import __version__
from openfly_agent.constants import CONFIG_NAME, MODEL_TYPE, PROCESSOR_CONFIG_NAME

CONFIGURATION_FILE = "configuration_openfly_agent.py"
MODELING_FILE = "modeling_openfly_agent.py"
PROCESSING_FILE = "processing_openfly_agent.py"
# file -> (what, package module, class)
_EXPORTS = {
    CONFIGURATION_FILE: ("config", "openfly_agent.model.pretrained_config", "OpenFlyAgentConfig"),
    MODELING_FILE: ("model", "openfly_agent.model.agent", "OpenFlyAgent"),
    PROCESSING_FILE: ("processor", "openfly_agent.model.processor", "OpenFlyProcessor"),
}
PROCESSOR_AUTO_MAP = {"AutoProcessor": f"{PROCESSING_FILE.removesuffix('.py')}.OpenFlyProcessor"}
AUTO_MAP = {
    "AutoConfig": f"{CONFIGURATION_FILE.removesuffix('.py')}.OpenFlyAgentConfig",
    "AutoModel": f"{MODELING_FILE.removesuffix('.py')}.OpenFlyAgent",
    **PROCESSOR_AUTO_MAP,
}

_TEMPLATE = '''"""OpenFly-Agent {what} for `trust_remote_code` loading: re-exports the class of the installed `openfly-agent`."""

try:
    from {module} import {name}
except ImportError as err:  # the model code is not duplicated here; it ships with the package
    raise ImportError(
        "This repository's model code lives in the `openfly-agent` package: "
        f"pip install 'openfly-agent>={version}' ({{err}})"
    ) from err

__all__ = ["{name}"]
'''


def write_remote_code(folder: str | Path) -> list[str]:
    """Write the re-export modules into `folder` and `auto_map` into its config.json (and processor config).

    Returns:
        The names of the modules written.

    Raises:
        ValueError: config.json is not an OpenFly-Agent config.
    """
    folder = Path(folder)
    for name, (what, module, cls) in _EXPORTS.items():
        (folder / name).write_text(_TEMPLATE.format(what=what, module=module, name=cls, version=__version__))
    _set_auto_map(folder / CONFIG_NAME, AUTO_MAP, expect_model_type=True)
    if (folder / PROCESSOR_CONFIG_NAME).is_file():
        _set_auto_map(folder / PROCESSOR_CONFIG_NAME, PROCESSOR_AUTO_MAP, expect_model_type=False)
    return list(_EXPORTS)


def remove_auto_map(folder: str | Path) -> None:
    """Drop `auto_map` from `folder/config.json` (a folder without the modules: nothing AutoModel could load)."""
    path = Path(folder) / CONFIG_NAME
    config = json.loads(path.read_text())
    if config.pop("auto_map", None) is not None:
        path.write_text(json.dumps(config, indent=2, sort_keys=True) + "\n")


def _set_auto_map(path: Path, auto_map: dict[str, str], expect_model_type: bool) -> None:
    config = json.loads(path.read_text())
    if expect_model_type and config.get("model_type") != MODEL_TYPE:
        raise ValueError(f"{path}: model_type is {config.get('model_type')!r}, expected {MODEL_TYPE!r}")
    config["auto_map"] = dict(auto_map)
    path.write_text(json.dumps(config, indent=2, sort_keys=True) + "\n")
