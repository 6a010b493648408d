"""Command-line shorthands of `eval.py` on top of draccus.

draccus reads lists as `--split=[test_seen,test_unseen]` and nested fields as `--sim.type=embedded`;
the issue's command line writes `--split test_seen test_unseen --sim embedded`. `normalize_argv`
rewrites the short forms into the draccus ones and leaves everything else untouched.
"""

from __future__ import annotations

import dataclasses
import typing

from openfly_agent.eval.config import EvalConfig

# Nested config sections that accept `--<section> <value>` as `--<section>.type=<value>`.
TYPE_SHORTHANDS = ("sim",)


def list_fields(config_class: type = EvalConfig) -> set[str]:
    """Names of the top-level fields whose type is a list."""
    hints = typing.get_type_hints(config_class)
    return {f.name for f in dataclasses.fields(config_class) if typing.get_origin(hints[f.name]) is list}


def normalize_argv(argv: list[str], config_class: type = EvalConfig) -> list[str]:
    """Rewrite `--<list field> a b c` into `--<list field>=[a,b,c]` and `--sim X` into `--sim.type=X`."""
    lists = list_fields(config_class)
    out: list[str] = []
    i = 0
    while i < len(argv):
        token = argv[i]
        name = token[2:] if token.startswith("--") and "=" not in token else None
        if name in lists:
            values = []
            while i + 1 < len(argv) and not argv[i + 1].startswith("--"):
                values.append(argv[i + 1])
                i += 1
            if len(values) == 1 and values[0].startswith("["):
                out.append(f"--{name}={values[0]}")
            else:
                out.append(f"--{name}=[{','.join(values)}]")
        elif name in TYPE_SHORTHANDS and i + 1 < len(argv) and not argv[i + 1].startswith("--"):
            out.append(f"--{name}.type={argv[i + 1]}")
            i += 1
        elif token.startswith("--") and "=" in token and token.split("=", 1)[0][2:] in TYPE_SHORTHANDS:
            out.append(f"--{token.split('=', 1)[0][2:]}.type={token.split('=', 1)[1]}")
        else:
            out.append(token)
        i += 1
    return out
