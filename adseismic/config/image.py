"""Imaging configuration (``adseismic image``): the forward sections (``model`` is the migration model), ``physics``,
``image`` (:class:`ImagingConfig`) and exactly one of ``true_model`` or ``observed``, parsed as fwi parses them
(:func:`adseismic.config.fwi.parse_fwi_config`: the same keys, files and checks). Imports no workflow.
"""
from __future__ import annotations

import pathlib
from dataclasses import dataclass, field
from pathlib import Path

from adseismic.config import forward, schema
from adseismic.config.common import ConfigError, _check_keys, _choice, _read_yaml
from adseismic.config.forward import ForwardConfig, refuse_forward_only
from adseismic.config.fwi import parse_fwi_config
from adseismic.config.parallel import ParallelConfig
from adseismic.config.schema import given, validate_section
from adseismic.data.model import Model

__all__ = ["IMAGE_METHODS", "ImageConfig", "ImagingConfig", "load_image_config", "parse_image_config"]

IMAGE_METHODS = schema.IMAGE_METHODS
IMAGE_SECTIONS = ("image", "true_model", "observed", "parallel")


@dataclass
class ImagingConfig:
    """The ``image`` section (units m). method: rtm | lsrtm; iterations: lsrtm's conjugate-gradient iterations;
    smoothing: Gaussian sigma (m) of the slowness smoothing that makes the background from the model; water_depth:
    depth (m) above which the background keeps the model as it is and the image is zero; illumination: compensate
    (rtm) / precondition (lsrtm) by the source illumination; epsilon: its stabiliser as a fraction of its maximum;
    laplacian: rtm image -> -laplacian(image)."""

    method: str = "rtm"
    iterations: int = 10
    smoothing: float = 0.0
    water_depth: float = 0.0
    illumination: bool = True
    epsilon: float = 0.001
    laplacian: bool = False


@dataclass
class ImageConfig:
    """An imaging run: ``forward.model`` is the migration model (smoothed by image.smoothing into the background);
    the data come from ``true_model`` (simulated) or ``observed`` (files, as fwi reads them); ``parallel``: acoustic
    RTM's and LSRTM's shots over workers (config.parallel; imaging.run.PooledBorn), None: one process."""

    forward: ForwardConfig
    image: ImagingConfig = field(default_factory=ImagingConfig)
    physics: str = "acoustic"
    true_model: Model | None = None
    observed: dict | None = None
    parallel: ParallelConfig | None = None


def _parse_image(raw, physics: str) -> ImagingConfig:
    v = given(validate_section(schema.Imaging, raw, "image"))
    out = ImagingConfig(**v)
    if physics == "elastic" and out.method == "lsrtm":
        raise ConfigError("image.method: lsrtm with physics: elastic is not available (there is no elastic Born "
                          "operator); use method: rtm (the elastic RTM images vp) or physics: acoustic")
    if physics == "elastic":
        if v.get("illumination"):
            raise ConfigError("image.illumination: true with physics: elastic; the elastic solver computes no source "
                              "illumination: drop the key (elastic RTM images are not compensated) or use physics: acoustic")
        out.illumination = False
    if out.method == "lsrtm" and out.laplacian:
        raise ConfigError("image.laplacian: true with method: lsrtm; the Laplacian filter is for RTM images (LSRTM "
                          "inverts for the velocity perturbation itself): drop it or use method: rtm")
    if "iterations" in v and out.method != "lsrtm":
        raise ConfigError(f"image.iterations: {out.iterations} with method: {out.method}; iterations are for "
                          f"method: lsrtm: drop the key or set method: lsrtm")
    return out


def parse_image_config(raw: dict, base_dir: Path | str | None = None, path: Path | None = None) -> ImageConfig:
    """Validate an imaging config: the forward sections plus ``image`` and exactly one of ``true_model`` or
    ``observed`` (checked as in fwi). Raises ConfigError naming the key, the value and the fix."""
    base_dir = pathlib.Path.cwd() if base_dir is None else pathlib.Path(base_dir)
    if not isinstance(raw, dict):
        raise ConfigError(f"config: {type(raw).__name__} is not a mapping; an image config has the sections "
                          f"{', '.join(forward.REQUIRED_SECTIONS + IMAGE_SECTIONS)} (and optionally physics, simulation)")
    _check_keys(raw, "", forward.SECTIONS + IMAGE_SECTIONS)
    physics = _choice(raw.get("physics") or "acoustic", "physics", schema.PHYSICS)
    refuse_forward_only(physics, "image", "migrate with physics: acoustic (model: the vp spec) or physics: elastic")
    if physics == "acoustic_vd":  # migration needs a smooth background's kinematics, which density does not change
        raise ConfigError("physics: acoustic_vd is not available for adseismic image (there is no density image, and "
                          "the migration background's travel times do not depend on the density); use physics: acoustic "
                          "with model: the vp spec (or physics: elastic)")
    image = _parse_image(raw.get("image"), physics)
    fwi = parse_fwi_config({k: v for k, v in raw.items() if k != "image"}, base_dir=base_dir, path=path)
    if getattr(fwi, "network", None) is not None:
        raise ConfigError("model.kind: nn is a parameterisation for fwi; an image needs the migration model itself: give "
                          "a velocity model (constant, layered, or a file)")
    model = getattr(fwi.forward.model, "vp", fwi.forward.model)  # (elastic: the P speed is imaged)
    if image.smoothing > 0:
        size = max(n * h for n, h in zip(model.shape, model.spacing))
        if image.smoothing > size:
            raise ConfigError(f"image.smoothing: {image.smoothing:g} m is larger than the model ({size:g} m across); "
                              f"give a Gaussian standard deviation below it (the background would be constant)")
    depth = model.extent[0][1]
    if image.water_depth >= depth:
        raise ConfigError(f"image.water_depth: {image.water_depth:g} m is at or below the model's bottom ({depth:g} m); "
                          f"the whole image would be zero: give the water's depth, or 0")
    return ImageConfig(fwi.forward, image, physics, fwi.true_model, fwi.observed, fwi.parallel)


def load_image_config(path) -> ImageConfig:
    """Read and validate an imaging YAML file (paths inside resolve from its folder)."""
    raw, path = _read_yaml(path)
    return parse_image_config(raw, base_dir=path.resolve().parent, path=path)
