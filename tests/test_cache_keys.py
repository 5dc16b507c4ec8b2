"""The cache keys of existing artefacts do not move by accident: a field added to a config enters
the keys only away from its default (sdexp.cache.KEY_UNLESS_DEFAULT), so every cache built before
it stays valid. A key moved here means every user's data and nets are rebuilt (hours for the
fleet): change the stored keys only with a deliberate format change, and say so."""
from sdexp.cache import config_key
from sdexp.config import DroneConfig, MeshConfig
from sdexp.model.dataset import dataset_key, dataset_spec
from tests.conftest import make_config

# the keys of the SOTA flower's and the fleet's donut's (seed 0) data, as of DATA_FORMAT 4 (the rotor
# thrust a traction over its disc, 2026-11-26: the deliberate change that last moved them; the
# fleet in results/fleet was built with these; results/sota and the others before it with the format before)
STORED = {("experiment=sota", "drone=flower"): "data-ec1665ee04831950"}


def test_the_committed_runs_data_keys_are_the_ones_their_caches_were_built_with():
    from sdexp.eval.fleet import job_config
    for overrides, key in STORED.items():
        assert dataset_key(dataset_spec(make_config(*overrides))) == key, overrides
    fleet = make_config("experiment=fleet")
    assert dataset_key(dataset_spec(job_config(fleet, "donut", 0, fleet.experiment.params))) == "data-510872cf98450b85"


def test_fields_added_with_list_defaults_stay_out_of_the_key_until_set():
    """default_factory fields (drone.rotors, drone.imus, ...) compare with the factory's value."""
    plain = config_key(DroneConfig())
    assert not {"rotors", "rotor_normals", "imus"} & set(plain)
    assert config_key(DroneConfig(imus=[[0.0, 1.0]]))["imus"] == [[0.0, 1.0]]
    assert not {"scale", "digest"} & set(config_key(MeshConfig()))
    assert config_key(MeshConfig(scale=0.001))["scale"] == 0.001


def test_a_content_digest_follows_every_value_and_nothing_else():
    """content_digest keys artefacts made from built objects (the shape-holding hover thrust of a
    drone as meshed): equal content, equal digest; any array, field or threads count, another."""
    from dataclasses import replace
    import numpy as np
    from sdexp.cache import content_digest
    from sdexp.config import SimConfig
    a = {"x": np.arange(6.0).reshape(2, 3), "n": 3}
    assert content_digest(a) == content_digest({"n": 3, "x": np.arange(6.0).reshape(2, 3)})
    assert content_digest(a) != content_digest({"x": np.arange(6.0).reshape(3, 2), "n": 3})   # shape
    assert content_digest(a) != content_digest({"x": np.arange(6, dtype=np.float32).reshape(2, 3), "n": 3})
    ulp = a["x"].copy()
    ulp[1, 2] = np.nextafter(ulp[1, 2], 10.0)   # one bit
    assert content_digest(a) != content_digest({"x": ulp, "n": 3})
    sim = SimConfig()
    assert content_digest(sim) == content_digest(replace(sim))
    assert content_digest(sim) != content_digest(replace(sim, threads=int(sim.threads) + 1))
