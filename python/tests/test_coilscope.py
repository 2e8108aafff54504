"""Truth-based tests of the Python package: simulate a real driver, identify it, compare
with the truth; the physics checked (energy of the suspension, a known transfer function)."""

import numpy as np
import pytest

import coilscope

FS = 48000.0


def test_drivers_and_parameters_round_trip():
    names = coilscope.drivers()
    assert "sb17cac35-4" in names
    p = coilscope.parameters("sb17cac35-4")
    assert p["format"] == "coilscope.parameters/1"
    assert coilscope.parameters(p) == p
    with pytest.raises(ValueError, match="Mms"):
        bad = dict(p)
        bad["Mms"] = -1.0
        coilscope.parameters(bad)


def test_simulate_holds_the_static_balance():
    p = coilscope.parameters("ptt4.0w04-01a")
    # A DC voltage: the current is U / Re(T) (the coil warms), and at rest the coil sits
    # where the suspension holds the force, Kms(x) x = Bl(x) i.
    u = np.full(int(2 * FS), 0.5)
    t = coilscope.simulate(p, u, FS)
    # Not the very last samples: the band-limited input sees the silence after the record.
    x = t["x"][-1000]
    i = t["i"][-1000]
    re_t = p["Re"] * (1 + p["thermal"]["alpha"] * t["tv"][-1000])
    assert abs(i / (0.5 / re_t) - 1) < 1e-6
    kms_x = coilscope.poly(p["Kms"], x) * x
    assert abs(kms_x / (coilscope.poly(p["Bl"], x) * i) - 1) < 1e-5


def test_linear_and_identify_find_the_truth():
    p = coilscope.parameters("ptt4.0w04-01a")
    u = coilscope.generate("pink", FS, 4.0, 0.3, seed=3, band=(5, 16000))
    t = coilscope.simulate(p, u, FS)
    lin = coilscope.linear(u, t["i"], FS, p["Mms"])
    bl = lin["parameters"]["Bl"]
    bl0 = bl if isinstance(bl, float) else bl[0]
    assert abs(bl0 / coilscope.poly(p["Bl"], 0.0) - 1) < 0.01
    assert abs(lin["parameters"]["Re"] / p["Re"] - 1) < 0.005
    # Large signal: pink noise reaching most of the range.
    u = coilscope.generate("pink", FS, 6.0, 2.5, seed=4, band=(10, 8000))
    t = coilscope.simulate(p, u, FS)
    r = coilscope.identify(u, t["i"], FS, p["Mms"], order=6)
    q = r["parameters"]
    lo, hi = r["fit"]["x_range"]
    xs = np.linspace(0.8 * lo, 0.8 * hi, 41)
    for key in ("Bl", "Kms"):
        err = np.max(np.abs(coilscope.poly(q[key], xs) / coilscope.poly(p[key], xs) - 1))
        assert err < 0.01, (key, err)
    assert r["uncertainty"]["Bl_band"]["sd"]


def test_measure_virtual_converges_and_replay_runs():
    r = coilscope.measure_virtual("sb17cac35-4", seed=2)
    assert r["fit"]["converged"], r["fit"].get("stop_reason")
    p = coilscope.parameters("sb17cac35-4")
    lo, hi = r["fit"]["x_range"]
    xs = np.linspace(lo, hi, 41)
    err = np.max(np.abs(coilscope.poly(r["parameters"]["Bl"], xs) / coilscope.poly(p["Bl"], xs) - 1))
    assert err < 0.02, err
    # The scale's source is said, as on the command line.
    assert "virtual driver's own Mms" in r["fit"]["Mms_source"]
    # A driver in a box is refused, as the command line refuses it: the box's air is no
    # suspension.
    with pytest.raises(ValueError, match="free air"):
        coilscope.measure_virtual(dict(p, enclosure={"type": "closed", "Vb": 0.012}))
    u = coilscope.generate("noise", FS, 10.0, 2.0, seed=5)
    t = coilscope.simulate(p, u, FS)
    rr = coilscope.measure_replay(u, t["i"], FS, p["Mms"])
    assert rr["parameters"]["Re"] > 0


def test_quasistatic_gives_the_command_lines_result():
    # The same workflow as `coilscope quasistatic`: the points, the fitted curves, the verdict.
    r = coilscope.quasistatic("sb17cac35-4", points=9, hold=1.0)
    p = coilscope.parameters("sb17cac35-4")
    assert len(r["quasi_static"]["points"]) >= 8
    lo, hi = r["fit"]["x_range"]
    xs = np.linspace(0.5 * lo, 0.5 * hi, 11)
    err = np.max(np.abs(coilscope.poly(r["parameters"]["Bl"], xs) / coilscope.poly(p["Bl"], xs) - 1))
    assert err < 0.03, err
    with pytest.raises(ValueError, match="--reach"):
        coilscope.quasistatic("sb17cac35-4", reach=1.5)
    with pytest.raises(ValueError, match="free air"):
        coilscope.quasistatic(dict(p, enclosure={"type": "closed", "Vb": 0.012}))


def test_distortion_and_errors():
    d = coilscope.distortion("sb17cac35-4", 40.0, 2.0)
    assert 1e-4 < d["HD2"] < 0.3 and "contributions" in d
    # The Volterra series of the same set beside it, as the command line prints it: at a
    # small level it agrees with the full model.
    low = coilscope.distortion("sb17cac35-4", 40.0, 0.3)
    assert abs(low["volterra"]["HD2_dB"] - 20 * np.log10(low["HD2"])) < 1.0, low["volterra"]
    assert low["volterra"]["kernels"]
    with pytest.raises(ValueError, match="sample rate"):
        coilscope.simulate("sb17cac35-4", np.zeros(100), 10.0)
    with pytest.raises(ValueError, match="differ in length"):
        coilscope.linear(np.zeros(100), np.zeros(99), FS, 0.01)
    with pytest.raises(ValueError, match="one-dimensional"):
        coilscope.simulate("sb17cac35-4", np.zeros((2, 2)), FS)


def _late(i, samples):
    """The current channel `samples` late (a fractional delay by the DFT's phase)."""
    n = len(i)
    f = np.fft.rfftfreq(n)
    return np.fft.irfft(np.fft.rfft(i) * np.exp(-2j * np.pi * f * samples), n)


def test_a_late_current_is_not_trusted_silently():
    # The command line exits 3 on it with `--chain none`; Python says the same.
    p = coilscope.parameters("sb17cac35-4")
    u = coilscope.generate("pink", FS, 6.0, 2.3, seed=7, band=(10, 8000))
    t = coilscope.simulate(p, u, FS)
    with pytest.warns(coilscope.NotTrustworthy, match="current-delay|residual"):
        r = coilscope.identify(u, _late(t["i"], 0.5), FS, p["Mms"], chain="none")
    assert r["fit"]["trustworthy"] is False
    assert r["fit"]["warnings"]
    # By default the skew is found and estimated with the driver: no warning, and Re right.
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error", coilscope.NotTrustworthy)
        r = coilscope.identify(u, _late(t["i"], 0.5), FS, p["Mms"])
    assert r["fit"]["trustworthy"] is True
    assert abs(r["parameters"]["Re"] / p["Re"] - 1) < 0.003
    assert r["chain"]["delay_i"] > 0


def test_a_linear_fit_of_a_large_signal_record_is_not_trusted_silently():
    p = coilscope.parameters("sb17cac35-4")
    u = coilscope.generate("pink", FS, 4.0, 2.3, seed=8, band=(10, 8000))
    t = coilscope.simulate(p, u, FS)
    with pytest.warns(coilscope.NotTrustworthy, match="large-signal-record|residual"):
        r = coilscope.linear(u, t["i"], FS, p["Mms"])
    assert r["fit"]["trustworthy"] is False
    codes = [w["code"] for w in r["fit"]["warnings"]]
    assert codes, r["fit"]


def _seas_zma(name):
    """A measured .zma of the SEAS L16RN-X (frequency, |Z|, phase in degrees) from the
    repository's test data."""
    import pathlib

    path = pathlib.Path(__file__).resolve().parents[2] / "crates/coilscope-ident/tests/data/seas_l16rnx" / name
    rows = [line.split() for line in path.read_text().splitlines()]
    rows = [r for r in rows if len(r) >= 3 and r[0].replace(".", "", 1).isdigit()]
    f, mag, ph = (np.array([float(r[k]) for r in rows]) for k in range(3))
    return f, mag * np.exp(1j * np.radians(ph))


def test_linear_impedance_keeps_below_the_break_up_as_the_command_line():
    import warnings

    f, z = _seas_zma("L16RNX_0g_242_27mV.zma")
    with warnings.catch_warnings():
        warnings.simplefilter("error", coilscope.NotTrustworthy)
        r = coilscope.linear_impedance(f, z, mms=0.0149)
    assert r["fit"]["trustworthy"] is True
    assert 1000.0 < r["fit"]["band_hz"][1] < 5206.0, r["fit"]["band_note"]
    assert "lumped model holds" in r["fit"]["band_note"]
    # Qms at fs with creep's loss, as Speakerbench gives it (1.995).
    assert abs(r["small_signal"]["Qms"] / 1.9953 - 1.0) < 0.05
    assert r["small_signal"]["Rms_fs"] > r["parameters"]["Rms"]
    # A band through the break-up is fitted as given, and is not trusted.
    with pytest.warns(coilscope.NotTrustworthy, match="model-misses-curve"):
        loud = coilscope.linear_impedance(f, z, mms=0.0149, band=(10.0, 20000.0))
    assert loud["fit"]["trustworthy"] is False
    # |Z| alone: said so, and the same figures.
    mag = coilscope.linear_impedance(f, np.abs(z), mms=0.0149, magnitude_only=True)
    assert "|Z| alone" in mag["fit"]["phase_note"]
    assert abs(mag["parameters"]["Bl"] / r["parameters"]["Bl"] - 1.0) < 0.01
    # Frequencies out of order are refused with the reason, not fitted.
    with pytest.raises(ValueError, match="increasing"):
        coilscope.linear_impedance(f[::-1], z[::-1], mms=0.0149)
    # A weighed mass with its sd: its share in what the scale moves, as `--mms 14.9g±0.3g`.
    w = coilscope.linear_impedance(f, z, mms=0.0149, mms_sd=0.0003)
    share = w["uncertainty"]["scale.Bl"]
    assert abs(share / (0.5 * 0.0003 / 0.0149 * w["parameters"]["Bl"]) - 1.0) < 1e-9
    assert abs(w["uncertainty"]["Bl"] - np.hypot(r["uncertainty"]["Bl"], share)) < 1e-9
    assert w["uncertainty"]["Re"] == r["uncertainty"]["Re"]
    with pytest.raises(ValueError, match="less than half the mass"):
        coilscope.linear_impedance(f, z, mms=0.0149, mms_sd=0.01)


def test_linear_enclosure_finds_the_box_as_the_command_line():
    import warnings

    driver = coilscope.parameters("sb17cac35-4")
    boxed = dict(driver, enclosure={"type": "vented", "Vb": 0.02, "fb": 38.0, "QL": 8.0, "Qp": 40.0})
    f = np.geomspace(5.0, 400.0, 300)
    z = coilscope.impedance(boxed, f)
    with warnings.catch_warnings():
        warnings.simplefilter("error", coilscope.NotTrustworthy)
        r = coilscope.linear_enclosure(f, z, driver)
    e = r["parameters"]["enclosure"]
    assert e["type"] == "vented", r["fit"]["models_note"]
    assert abs(e["Vb"] / 0.02 - 1.0) < 0.02 and abs(e["fb"] / 38.0 - 1.0) < 0.01, e
    assert r["uncertainty"]["enclosure.Vb"] >= 0.0
    # The wrong driver's set leaves the impedance unexplained: said, not taken silently.
    with pytest.warns(coilscope.NotTrustworthy, match="residual-above-noise"):
        coilscope.linear_enclosure(f, z, "ptt4.0w04-01a")
    with pytest.raises(ValueError, match="passive_radiator"):
        coilscope.linear_enclosure(f, z, driver, enclosure="sealed")


def test_identify_in_a_closed_box_finds_the_driver_and_its_box_as_the_command_line():
    import warnings

    driver = coilscope.parameters("sb17cac35-4")
    boxed = dict(driver, enclosure={"type": "closed", "Vb": 0.012, "QL": 10.0})
    lo, hi = driver["x_range"]
    u = coilscope.generate("pink", FS, 6.0, 1.0, seed=4, band=(10, 8000))
    # Scaled so that the cone reaches about 70 % of its range.
    u = u * 0.7 * min(hi, -lo) / np.max(np.abs(coilscope.simulate(boxed, u, FS)["x"]))
    t = coilscope.simulate(boxed, u, FS)
    with warnings.catch_warnings():
        warnings.simplefilter("error", coilscope.NotTrustworthy)
        r = coilscope.identify(u, t["i"], FS, driver["Mms"], chain="none", enclosure="closed", sd=driver["Sd"], vb=0.012)
    q = r["parameters"]
    assert q["enclosure"]["type"] == "closed"
    assert abs(q["enclosure"]["QL"] / 10.0 - 1) < 0.25, q["enclosure"]
    a, b = r["fit"]["x_range"]
    xs = np.linspace(a, b, 41)
    for key in ("Bl", "Kms"):
        # Kms is the suspension's own, without the box air's stiffness.
        err = np.max(np.abs(coilscope.poly(q[key], xs) / coilscope.poly(driver[key], xs) - 1))
        assert err < 0.01, (key, err)
    assert r["uncertainty"]["enclosure.QL"] > 0
    # What the command line refuses, Python refuses with the same reason.
    with pytest.raises(ValueError, match="--vb"):
        coilscope.identify(u, t["i"], FS, driver["Mms"], chain="none", enclosure="closed", sd=driver["Sd"])
    with pytest.raises(ValueError, match="Sd"):
        coilscope.identify(u, t["i"], FS, driver["Mms"], enclosure="closed", vb=0.012)
    with pytest.raises(ValueError, match="passive_radiator"):
        coilscope.identify(u, t["i"], FS, driver["Mms"], enclosure="sealed", sd=driver["Sd"])


def test_a_misspelt_key_is_a_python_warning():
    p = coilscope.parameters("sb17cac35-4")
    p["Rmss"] = 1.0
    with pytest.warns(coilscope.MisspeltKey, match="`Rmss`.*`Rms`"):
        back = coilscope.parameters(p)
    assert back["Rmss"] == 1.0 and back["Rms"] == p["Rms"]
