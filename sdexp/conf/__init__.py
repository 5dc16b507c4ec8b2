"""The configs (Hydra's primary config and its groups), shipped inside the package so that any
install and any working directory find them: Hydra reads them from ``SEARCH_PATH`` and the code
through :func:`names` and :func:`read`, never by a path relative to the source tree.

Importing it registers the schema (``base_config`` in config.yaml's defaults list, each
experiment's params in ``experiment_params``) and the resolvers the files use, so whatever
composes them (the cli, a test's compose) has them."""
from __future__ import annotations

from importlib.resources import files

from omegaconf import DictConfig, OmegaConf

from sdexp import experiment_params
from sdexp.config import register

register()
experiment_params.register()
if not OmegaConf.has_resolver("sdexp.drones"):
    OmegaConf.register_new_resolver("sdexp.drones", lambda: drone_lines())

SEARCH_PATH = "pkg://sdexp.conf"
MODULE = "sdexp.conf"


def _file(*parts: str):
    node = files(MODULE)
    for part in parts:
        node = node.joinpath(part)
    return node


def names(group: str) -> list[str]:
    """The options of a config group (its .yaml files), sorted."""
    return sorted(f.name[:-len(".yaml")] for f in _file(group).iterdir() if f.name.endswith(".yaml"))


def drone_lines() -> str:
    """``sdexp --help``'s drone list (``${sdexp.drones:}`` in conf/hydra/help/sdexp.yaml): the
    paper's drones, 3D then 2D, so that a drone's YAML is listed without a second edit."""
    by_dim = {3: [], 2: []}
    for name in paper_drones():
        by_dim[int(read("drone", name).get("dim", 3))].append(name)
    return "\n".join(f"    {'  '.join(by_dim[d])}   ({d}D)" for d in (3, 2) if by_dim[d])


def paper_drones() -> list[str]:
    """The paper's twelve drones: the drone configs made by a shape generator. The others
    (``shape: file``: custom, the template, and tripod, the example) are drones of one's own,
    flown by name; the experiments and environments that run "every drone" run these."""
    return [n for n in names("drone") if read("drone", n).get("shape") != "file"]


def drone(name: str):
    """conf/drone/<name>.yaml as a DroneConfig (the experiments that run several drones), its
    defaults list applied as Hydra would (tripod.yaml builds on custom.yaml) and read under the key
    ``drone``, where its interpolations (``${sdexp.count:drone.rotors}``) look."""
    from sdexp.config import DroneConfig
    root = OmegaConf.create({"drone": OmegaConf.merge(OmegaConf.structured(DroneConfig), *_layers("drone", name))})
    return OmegaConf.to_object(root.drone)


def _layers(group: str, name: str) -> list[DictConfig]:
    """The files a group option composes, in merge order: its defaults list (options of the same
    group, each with its own), ``_self_`` where listed, else last (Hydra's rule)."""
    own = read(group, name)
    if own is None:
        raise FileNotFoundError(f"no config {group}/{name}.yaml")
    entries = list(own.pop("defaults", None) or [])
    if "_self_" not in entries:
        entries.append("_self_")
    return [layer for e in entries for layer in ([own] if e == "_self_" else _layers(group, str(e)))]


def read(*parts: str) -> DictConfig | None:
    """The file ``<parts...>.yaml`` as written (no defaults list applied), or None if there is
    none: ``read("drone", "flower")``, ``read("config")``."""
    f = _file(*parts[:-1], f"{parts[-1]}.yaml")
    if not f.is_file():
        return None
    with f.open("r", encoding="utf-8") as stream:
        return OmegaConf.load(stream)
