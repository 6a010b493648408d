"""Value checks shared by the model config sections (model/config.py, model/vision/config.py, model/grounding/config.py);
stdlib only."""

from __future__ import annotations


def check_choice(section: str, name: str, value: str, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise ValueError(f"{section}.{name}={value!r} is not supported; use one of {list(choices)}")


def check_positive(section: str, name: str, value: float) -> None:
    if value <= 0:
        raise ValueError(f"{section}.{name} must be > 0, got {value}")
