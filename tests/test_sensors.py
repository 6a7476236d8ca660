"""Sensor models: geometry from the data sheets and from a real PP reply."""

import math

import numpy as np
import pytest

from gtsjax import InputError, get_model
from gtsjax.sensors import MODELS, URG_04LX, UTM_30LX, SensorModel


def test_urg04lx_geometry():
    m = URG_04LX
    assert m.n_beams == 682  # steps 44..725 of 1024
    assert m.angles[384 - 44] == 0.0  # the front step points along x of S
    assert math.isclose(m.angle_increment, 2 * math.pi / 1024)
    assert math.isclose(m.angle_min, -340 * 2 * math.pi / 1024)
    assert (m.range_min, m.range_max, m.period) == (0.02, 5.6, 0.1)
    assert not m.has_intensity


def test_utm30lx_geometry():
    m = UTM_30LX
    assert m.n_beams == 1081 and m.angles[540] == 0.0
    assert math.isclose(m.angle_min, -3 * math.pi / 4) and math.isclose(m.angle_max, 3 * math.pi / 4)
    assert (m.range_min, m.range_max, m.rate_hz) == (0.1, 30.0, 40.0)
    assert m.has_intensity


def test_noise_model_piecewise():
    n = URG_04LX.noise
    np.testing.assert_allclose(n.std(np.array([0.5, 1.0, 2.0, 4.0])), [0.003, 0.003, 0.006, 0.012])
    np.testing.assert_allclose(UTM_30LX.noise.std(np.array([5.0, 20.0])), [0.010, 0.015])


def test_pp_fields_round_trip():
    for m in MODELS.values():
        assert SensorModel.from_pp(m.pp_fields()) == m


def test_from_real_utm_pp_capture(shared_dir):
    raw = (shared_dir / "data/scip/PP_utm30lx-ew_from_comment.bin").read_bytes().decode()
    fields = {}
    for line in raw.splitlines()[2:]:
        if ":" in line:
            key, rest = line.split(":", 1)
            fields[key] = rest[: rest.rindex(";")]
    m = SensorModel.from_pp(fields)
    assert m.name == "UTM-30LX" and m.has_intensity  # the EW variant maps onto the known model
    assert (m.n_beams, m.afrt, m.ares, m.scan_rpm) == (1081, 540, 1440, 2400)
    assert (m.dmin_mm, m.dmax_mm) == (23, 60000)  # geometry and window come from the reply itself


def test_from_pp_missing_field_is_one_line():
    fields = URG_04LX.pp_fields()
    del fields["AFRT"]
    with pytest.raises(InputError, match="missing field.*AFRT"):
        SensorModel.from_pp(fields)


def test_unknown_model_from_pp_and_by_name():
    fields = dict(URG_04LX.pp_fields(), MODL="ACME-1(prototype)")
    m = SensorModel.from_pp(fields)
    assert m.name == "ACME-1" and m.n_beams == 682
    assert get_model("utm-30lx-ew") is UTM_30LX
    assert get_model("URG-04LX-UG01").name == "URG-04LX-UG01"
    with pytest.raises(InputError, match="unknown sensor model"):
        get_model("LMS-100")
