"""The family records (``gnwarp.sim.families``): name parsing, sizes, initial-state spec."""
import numpy as np
import pytest

from gnwarp.data.generation import initial_states
from gnwarp.sim import systems
from gnwarp.sim.families import FAMILIES, family_name, family_of, parse_name


def test_names_parse_into_family_and_size():
    assert [(f.name, n) for f, n in map(parse_name, ["swimmer6", "swimmer", " Pendulum ", "swimmer15"])] == [
        ("swimmer", 6), ("swimmer", None), ("pendulum", None), ("swimmer", 15)]
    assert family_name("swimmer12") == "swimmer" and family_name("cheetah") == "cheetah"
    # a name that is not built-in is its own family (a user MJCF file's stem), not cut at its digits
    assert family_of("robot2") is None and family_name("robot2") == "robot2"
    assert list(FAMILIES) == systems.names()


@pytest.mark.parametrize("bad,match", [("swimmer2", "3 to 15 links"), ("pendulum2", "unknown system"),
                                       ("walker_", "unknown system"), ("", "unknown system")])
def test_unknown_names_raise_clearly(bad, match):
    with pytest.raises(ValueError, match=match):
        parse_name(bad)
    with pytest.raises(ValueError, match=match):
        systems.make(bad)


def test_family_record_drives_make_and_initial_states():
    for name in ("pendulum", "swimmer4", "jaco"):
        fam, _ = parse_name(name)
        s = systems.make(name)
        assert (s.dt, s.substeps, s.translation_invariant) == (fam.dt, fam.substeps, fam.translation_invariant)
    assert systems.make("swimmer").name == "swimmer6" == f"swimmer{FAMILIES['swimmer'].default_links}"
    # unlimited hinges: full circle (pendulum) against +-0.1 rad around the reference pose (swimmer's rootz)
    rng = np.random.default_rng(0)
    q, _ = initial_states(systems.make("pendulum"), 200, rng)
    assert FAMILIES["pendulum"].full_circle and np.abs(q).max() > 3.0
    s = systems.make("swimmer6")
    q, _ = initial_states(s, 200, rng)
    assert not FAMILIES["swimmer"].full_circle and 0.05 < np.abs(q[:, 2] - s.model.qpos0[2]).max() <= 0.1
