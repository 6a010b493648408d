"""Value checks shared by the model config sections (model/config.py, model/vision/config.py, model/grounding/config.py);
stdlib only."""

from __future__ import annotations


def check_choice(section: str, name: str, value: str, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise ValueError(f"{section}.{name}={value!r} is not supported; use one of {list(choices)}")


def check_positive(section: str, name: str, value: float) -> None:
    if value <= 0:
        raise ValueError(f"{section}.{name} must be > 0, got {value}")


def fill_tiny_fields(section: str, cfg, is_tiny: bool, defaults: dict[str, int]) -> None:
    """Tiny preset: fill the unset tiny-only fields with `defaults`. Other presets: reject any that is set."""
    for name, default in defaults.items():
        value = getattr(cfg, name)
        if is_tiny and value is None:
            setattr(cfg, name, default)
        elif not is_tiny and value is not None:
            raise ValueError(
                f"{section}.{name}={value} is read by the tiny preset only; {section}.preset={cfg.preset} fixes "
                f"the architecture, so remove {section}.{name} (or use {section}.preset=tiny)"
            )
