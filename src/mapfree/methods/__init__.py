"""The method registry: a method is a string a user can type.

A method is either a *matching* pipeline (matcher + options, depth spec, solver + options) or another kind
(``regression``). ``KINDS`` names each kind's factory as ``"module:function"``, imported only when a method of that
kind is first built. Names of the form ``{matcher}_{solver}_{depth}`` (``sift_emat_dptkitti``,
``aliked-lightglue_pnp_sensor``) are parsed on the fly; anything else is a registered method (the best offline
presets, the two-view and MicKey presets, the published RPR models), a YAML file under ``configs/methods/`` or a
path to one.

The package's modules: ``base`` (the ``Method`` record and the kinds' factories), ``names`` (preset names),
``yamlconfig`` (method YAML files' keys and types), ``rules`` (the depth a method needs, its components' options),
``registry`` (``get``, ``register``, cascades, ``load_yaml``, ``list_methods``), ``needs`` (what a method needs to
run: packages, weights) and ``presets`` (the registered presets). Everything public is importable from
``mapfree.methods``.
"""

from __future__ import annotations

from ..method_names import BEST_OFFLINE, BEST_OFFLINE_REFERENCE_DEPTH
from .base import DEPTH_ALIASES, KINDS, Method, factory, register_kind
from .names import MATCHERS, OFFLINE_MATCHERS, PAPER_THRESHOLD_PX, SOLVERS, parse_name, preset_name
from .needs import all_weight_models, requirements, weight_models
from .presets import register_presets
from .registry import _REGISTRY as _REGISTRY  # the registered methods (tests register their own)
from .registry import (
    CASCADE,
    CASCADE_SEPARATOR,
    DEFAULT_ACCEPT,
    cascade_method,
    check_cascade_options,
    get,
    list_methods,
    load_yaml,
    parse_cascade,
    register,
)
from .rules import LIFTING_SOLVERS, QUERY_DEPTH_SOLVERS, check_options, depth_free_problem, query_depth_fallback
from .yamlconfig import YAML_KEY_TYPES, check_yaml_types, config_dirs

__all__ = [
    "Method",
    "MATCHERS",
    "OFFLINE_MATCHERS",
    "SOLVERS",
    "DEPTH_ALIASES",
    "BEST_OFFLINE",
    "BEST_OFFLINE_REFERENCE_DEPTH",
    "PAPER_THRESHOLD_PX",
    "get",
    "list_methods",
    "requirements",
    "register",
    "register_kind",
    "factory",
    "KINDS",
    "parse_name",
    "preset_name",
    "load_yaml",
    "config_dirs",
    "check_options",
    "query_depth_fallback",
    "depth_free_problem",
    "QUERY_DEPTH_SOLVERS",
    "LIFTING_SOLVERS",
    "weight_models",
    "all_weight_models",
    "CASCADE",
    "CASCADE_SEPARATOR",
    "cascade_method",
    "parse_cascade",
    "check_cascade_options",
    "DEFAULT_ACCEPT",
    "YAML_KEY_TYPES",
    "check_yaml_types",
]

register_presets()
