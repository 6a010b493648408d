"""A registered config variant is its config class and the builder of its module, as timm's `@register_model`
ties a name to its constructor in one place; stdlib only.

The model config's registered sections (`vision`, `llm`, `grounding`, `memory.encoding`; each a draccus
`ChoiceRegistry` whose `type:` names the variant) mix in `BuiltChoice`. The module that implements a variant
registers its builder on the variant's config class, and the section's config builds its module with `build`:

    @TinyCnnVisionConfig.register_builder      # model/vision/conv.py
    class ConvVisionBackbone(nn.Module): ...

    backbone = cfg.vision.build()              # ConvVisionBackbone(cfg.vision)

so nothing else dispatches on `type`. The configs stay free of torch: the builders live with the modules, which
register them when imported; each section's `build_*` / `make_*` function imports every module of its variants
(model/vision/backbone.py, model/language/llm.py, model/grounding/head.py, model/factory.py).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

Builder = TypeVar("Builder", bound=Callable[..., Any])


class BuiltChoice:
    """Mixin of a registered config section whose variants each build their module (`register_builder`, `build`).

    A variant's builder is its own: a variant that subclasses another registers its builder too.
    """

    @classmethod
    def register_builder(cls, builder: Builder) -> Builder:
        """Decorator: `builder(cfg, *args)` builds this variant's module (a class or a function; returned as is).

        Raises:
            TypeError: the variant has another builder already.
        """
        known = vars(cls).get("_builder")
        if known is not None and known.__qualname__ != builder.__qualname__:
            raise TypeError(
                f"{cls.__name__} is built by {known.__qualname__} already, not {builder.__qualname__}"
            )
        cls._builder = builder
        return builder

    @classmethod
    def builder(cls) -> Callable[..., Any]:
        """The registered builder of this variant.

        Raises:
            TypeError: none is registered (the module that implements the variant was not imported).
        """
        builder = vars(cls).get("_builder")
        if builder is None:
            raise TypeError(
                f"no builder is registered for {cls.__name__}: import the module that implements it (or register "
                f"one with @{cls.__name__}.register_builder)"
            )
        return builder

    def build(self, *args: Any, **kwargs: Any) -> Any:
        """This variant's module: `builder(self, *args, **kwargs)`."""
        return self.builder()(self, *args, **kwargs)
