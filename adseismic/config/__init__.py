"""YAML run configuration: one schema per workflow, validated before any work is done.

- :mod:`adseismic.config.schema`: the declarative schema (pydantic) of every section: each key's type, unit,
  default and meaning; the JSON Schema (``adseismic schema``), docs/config.md (docs/gen_config.py) and the
  templates of ``adseismic init`` come from it. The parsers below validate each section with it, then make
  the cross-field checks a schema cannot say;
- :mod:`adseismic.config.common`: :class:`ConfigError` (message starts with the dotted key path,
  says what was found and how to fix it), the shared value validators and YAML reading;
- :mod:`adseismic.config.forward`: forward runs (:class:`ForwardConfig`, :func:`load_config`);
- :mod:`adseismic.config.fwi`: inversions (:class:`FWIConfig`, :func:`load_fwi_config`);
- :mod:`adseismic.config.locate`: event location (:class:`LocateConfig`, :func:`load_locate_config`);
- :mod:`adseismic.config.image`: imaging, RTM and LSRTM (:class:`ImageConfig`, :func:`load_image_config`);
- :mod:`adseismic.config.parallel`: the optional ``parallel:`` section of fwi and forward (shots over Dask workers
  or the devices of one process).

Loading or parsing a config imports no workflow (nothing of adseismic.inversion, .location,
.solve, .cli or .bench); only the data layer (adseismic.data.models) for the velocity models.
"""
from adseismic.config.common import ConfigError
from adseismic.config.forward import ForwardConfig, GeometryConfig, OutputConfig, SimulationConfig, WaveletConfig, load_config, parse_config
from adseismic.config.fwi import FWIConfig, InversionConfig, load_fwi_config, parse_fwi_config
from adseismic.config.image import ImageConfig, load_image_config, parse_image_config
from adseismic.config.locate import LocateConfig, load_locate_config, parse_locate_config

__all__ = [
    "ConfigError",
    "ForwardConfig",
    "FWIConfig",
    "LocateConfig",
    "ImageConfig",
    "GeometryConfig",
    "OutputConfig",
    "WaveletConfig",
    "SimulationConfig",
    "InversionConfig",
    "load_config",
    "parse_config",
    "load_fwi_config",
    "parse_fwi_config",
    "load_locate_config",
    "parse_locate_config",
    "load_image_config",
    "parse_image_config",
]
