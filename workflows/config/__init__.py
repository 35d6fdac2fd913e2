"""Silva's configuration: YAML validated into typed, frozen objects.

A configuration has six sections (``data``, ``tiling``, ``features``, ``cascade``,
``cluster``, ``output``); every key has a default, so an empty file (or no file) is valid
until data is given. :func:`load_config` reads a YAML file, applies ``--set KEY=VALUE``
overrides to the raw mapping, then validates everything at once. Every problem becomes a
:class:`~pipeline.errors.ConfigError` with one line that names the dotted key, what was
received and what is allowed::

    config error: unknown key 'tiling.chunksize' (did you mean 'chunk_size'?)
    config error: features.r1 must be > 0, got -1

A key left empty in YAML (``n_estimators:``) means its default. Derived values are
resolved during validation: ``features.r2`` becomes ``r1 / 2`` and ``tiling.halo`` becomes
the features' reach plus a context radius per later cascade stage
(:func:`pipeline.cascade.one_pass_halo`) when unset, so :func:`dump_config` writes out exactly
what a run used and loading that text again gives an equal configuration.

Modules: :mod:`~workflows.config.schema` (the sections), :mod:`~workflows.config.loading`
(YAML, paths, overrides), :mod:`~workflows.config.messages` (one-line errors),
:mod:`~workflows.config.fields` (field types), :mod:`~workflows.config.inputs` (the input
tiles the data section names). The fingerprint of a step's keys is
:mod:`workflows.run.fingerprint`'s.
"""

from workflows.config.inputs import expand_inputs
from workflows.config.loading import dump_config, load_config, validate_config
from workflows.config.schema import ClusterConfig, SilvaConfig

__all__ = [
    "ClusterConfig",
    "SilvaConfig",
    "dump_config",
    "expand_inputs",
    "load_config",
    "validate_config",
]
