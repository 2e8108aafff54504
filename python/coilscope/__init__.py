"""coilscope from Python: large-signal loudspeaker parameters from voltage and current.

Signals are numpy arrays in SI units (V, A, m, m/s, K); parameter sets and results are dicts
in the coilscope file contract (``coilscope.parameters/1``, ``coilscope.result/1``): power
series as ascending coefficient lists in metres, uncertainties under ``uncertainty``. A
parameter set may be given as such a dict, a result dict, an embedded driver's name (see
:func:`drivers`), a drawn driver (``population:SEED``) or a JSON file's path. Errors raise
``ValueError`` with the message the command line prints.

A result that is not trustworthy (``result["fit"]["trustworthy"]`` false: the command line
exits 3 on it) comes back with its warnings under ``result["fit"]["warnings"]``, and raises a
Python warning of the category :class:`NotTrustworthy` that names them, so that it is never
taken silently. ``warnings.simplefilter("error", coilscope.NotTrustworthy)`` makes it an
exception.

>>> import coilscope
>>> p = coilscope.parameters("sb17cac35-4")
>>> u = coilscope.generate("pink", 48000, 4.0, 2.0, band=(10, 8000))
>>> trace = coilscope.simulate(p, u, 48000)
>>> result = coilscope.identify(u, trace["i"], 48000, mms=p["Mms"])
"""

import json
import warnings

import numpy as np

from . import _coilscope as _c

__all__ = ["NotTrustworthy", "MisspeltKey", "drivers", "parameters", "generate", "simulate", "linear", "linear_impedance", "linear_enclosure", "impedance", "identify", "identify_file", "identify_lot", "read_recording", "write_recording", "measure_virtual", "measure_replay", "distortion", "quasistatic", "poly"]


class NotTrustworthy(UserWarning):
    """A result that its own checks do not trust (``fit.trustworthy`` false): the command
    line exits 3 on it. The message names each warning (its code and its text)."""


def _checked(text, what):
    """A result dict from JSON text, with a :class:`NotTrustworthy` warning when its own
    checks do not trust it."""
    r = json.loads(text)
    fit = r.get("fit", {})
    if fit.get("trustworthy") is not True:
        named = [f"[{w.get('code')}] {w.get('message')}" for w in fit.get("warnings") or []]
        reason = fit.get("stop_reason") if not named else None
        detail = "; ".join(named) if named else (reason or "its fit did not converge")
        warnings.warn(f"{what}: the result is not trustworthy (fit.trustworthy is false): {detail}", NotTrustworthy, stacklevel=3)
    return r


class MisspeltKey(UserWarning):
    """A key of a parameter set that coilscope does not read but that is one or two edits from
    one it does (``Bll`` for ``Bl``): the set loads, without the parameter meant. The command
    line prints the same warning."""


def _spec(p):
    s = json.dumps(p) if isinstance(p, dict) else str(p)
    if isinstance(p, dict) or s.endswith(".json"):
        for key, meant in _c.near_miss_keys(s):
            warnings.warn(f"parameters: key `{key}` is not one coilscope reads (kept as is); did you mean `{meant}`?", MisspeltKey, stacklevel=3)
    return s


def _floats(a, name):
    a = np.asarray(a, dtype=float)
    if a.ndim != 1:
        raise ValueError(f"{name}: a one-dimensional array of samples is needed, got shape {a.shape}")
    return a.tolist()


def drivers():
    """The embedded real drivers' names (Klippel LSI parameters)."""
    return list(_c.drivers())


def parameters(spec):
    """A parameter set as a dict (validated): from a dict, a result dict, a name or a file."""
    return json.loads(_c.parameters(_spec(spec)))


def poly(coefficients, x):
    """Evaluate a contract power series (a number or ascending coefficients in metres) at x (m)."""
    c = np.atleast_1d(np.asarray(coefficients, dtype=float))
    return np.polynomial.polynomial.polyval(np.asarray(x, dtype=float), c)


def generate(kind, fs, seconds, rms, seed=1, band=None, freq=None, tones=30, fade=0.05):
    """A seeded excitation (V): noise (IEC 60268-1), pink, sine, multitone, sweep, readable."""
    return np.asarray(_c.generate(kind, float(fs), float(seconds), float(rms), int(seed), None if band is None else (float(band[0]), float(band[1])), None if freq is None else float(freq), int(tones), float(fade)))


def simulate(params, u, fs):
    """The virtual transducer driven by voltage u (V): dict of arrays x, v, i, tv, tm."""
    x, v, i, tv, tm = _c.simulate(_spec(params), float(fs), _floats(u, "u"))
    return {"u": np.asarray(u, dtype=float), "x": np.asarray(x), "v": np.asarray(v), "i": np.asarray(i), "tv": np.asarray(tv), "tm": np.asarray(tm)}


def linear(u, i, fs, mms, chain="detect", mms_sd=0.0):
    """Small-signal (Thiele/Small) fit of a record, Mms given (kg): the result dict.

    ``chain``: ``detect`` (estimate the recording chain where the record shows one), ``auto``
    or ``none``, as ``coilscope linear --chain``. ``mms_sd``: the mass's sd (kg), carried
    into Bl, Kms, Rms and Mms as ``--mms 15.3g±0.3g`` is (``uncertainty["scale.Bl"]`` its
    share); 0 takes the mass as exact. Warns :class:`NotTrustworthy` where the command line
    exits 3."""
    return _checked(_c.linear(_floats(u, "u"), _floats(i, "i"), float(fs), float(mms), str(chain), float(mms_sd)), "linear")


def linear_impedance(f, z, mms, band=None, magnitude_only=False, mms_sd=0.0):
    """Small-signal fit of a measured impedance curve (``coilscope linear --impedance``):
    ``f`` in Hz, ``z`` complex in ohm, Mms given (kg). Without ``band`` (Hz, ``(lo, hi)``) the
    fit keeps to where the lumped model holds, below the cone's break-up, and
    ``result["fit"]["band_note"]`` says where that is. Qms and Qts in ``small_signal`` are at
    fs with creep's loss (``Rms_fs``). ``magnitude_only``: only ``abs(z)`` is data (a file
    without phase), fitted to the magnitude alone (``result["fit"]["phase_note"]``).
    ``mms_sd`` as in :func:`linear`. Warns :class:`NotTrustworthy` where the command line
    exits 3."""
    z = np.asarray(z, dtype=complex)
    if magnitude_only:
        z = np.abs(z).astype(complex)
    b = None if band is None else (float(band[0]), float(band[1]))
    return _checked(_c.linear_impedance(_floats(f, "f"), _floats(z.real, "z"), _floats(z.imag, "z"), float(mms), b, bool(magnitude_only), float(mms_sd)), "linear_impedance")


def impedance(params, f):
    """The small-signal impedance (complex, ohm) of a parameter set at ``f`` (Hz): the
    network of the one model, with the set's box (``enclosure``) where it has one."""
    re, im = _c.impedance(_spec(params), _floats(f, "f"))
    return np.asarray(re) + 1j * np.asarray(im)


def linear_enclosure(f, z, driver, enclosure="auto", sp=None, magnitude_only=False):
    """The box a known driver works into, from its impedance in the box (``coilscope linear
    --enclosure``): ``f`` in Hz, ``z`` complex in ohm, ``driver`` the driver's own set
    (measured in free air, with Sd), ``enclosure`` one of ``closed``, ``vented``,
    ``passive_radiator`` or ``auto`` (the type from the data; ``result["fit"]["models_note"]``
    says why), ``sp`` a passive radiator's area (m^2). The box comes back as
    ``result["parameters"]["enclosure"]``, its sds under ``uncertainty["enclosure.Vb"]`` and
    the like. Warns :class:`NotTrustworthy` where the command line exits 3."""
    z = np.asarray(z, dtype=complex)
    if magnitude_only:
        z = np.abs(z).astype(complex)
    return _checked(_c.linear_enclosure(_floats(f, "f"), _floats(z.real, "z"), _floats(z.imag, "z"), _spec(driver), str(enclosure), None if sp is None else float(sp), bool(magnitude_only)), "linear_enclosure")


def identify(u, i, fs, mms, order=None, chain="detect", enclosure=None, sd=None, vb=None, port_area=None, sp=None, mms_sd=0.0):
    """Large-signal identification of a record (Mms given, kg): the result dict.

    ``chain`` as in :func:`linear`. ``enclosure``: the driver is in a box of this type
    (``closed``, ``vented``, ``passive_radiator`` or ``auto``), identified with it as
    ``coilscope identify --enclosure`` does; it needs ``sd`` (m^2), a closed box its net volume
    ``vb`` (m^3); ``port_area`` and ``sp`` (m^2) where known. ``mms_sd`` as in
    :func:`linear` (into the Bl and Kms bands too). Warns :class:`NotTrustworthy` where the
    command line exits 3."""
    opt = lambda v: None if v is None else float(v)
    return _checked(
        _c.identify(
            _floats(u, "u"), _floats(i, "i"), float(fs), float(mms), None if order is None else int(order), str(chain),
            None if enclosure is None else str(enclosure), opt(sd), opt(vb), opt(port_area), opt(sp),
            float(mms_sd),
        ),
        "identify",
    )


def read_recording(path):
    """A recording (WAV of 2 or 3 channels, as the command line reads it, its sidecar's scales
    applied): a dict ``{"fs", "u", "i", "x"}`` of numpy arrays (``x`` None without a laser)."""
    fs, u, i, x = _c.read_recording(str(path))
    return {"fs": fs, "u": np.asarray(u), "i": np.asarray(i), "x": None if x is None else np.asarray(x)}


def write_recording(path, u, i, fs, x=None):
    """Write a recording as the command line does (32-bit float WAV, written atomically)."""
    _c.write_recording(str(path), int(fs), _floats(u, "u"), _floats(i, "i"), None if x is None else _floats(x, "x"))


def identify_file(path, mms, **options):
    """:func:`identify` on a recording file (``coilscope identify REC.wav --mms KG``): the result
    dict, with the file's path under ``result["recording"]``. ``options`` as :func:`identify`'s.
    A plain module-level function, so that a cluster's workers can run it (see
    :func:`identify_lot`)."""
    r = read_recording(path)
    result = identify(r["u"], r["i"], r["fs"], mms, **options)
    result["recording"] = str(path)
    return result


def identify_lot(paths, mms, client=None, **options):
    """:func:`identify_file` on each of ``paths`` (one ``mms`` for all, or one per path): the
    results in the order of ``paths``.

    With ``client`` (a ``dask.distributed.Client``), the records are identified on its cluster,
    one task per record, scheduled by Dask; without, one after the other here. Each result is
    the one a single run gives: a record's identification depends on nothing but its record and
    options. A result that is not trustworthy says so under ``result["fit"]["trustworthy"]``
    (the warning a worker raises stays in the worker's log)::

        from dask.distributed import Client, LocalCluster
        with LocalCluster(n_workers=4, threads_per_worker=1) as cluster, Client(cluster) as client:
            results = coilscope.identify_lot(sorted(glob.glob("lot/*.wav")), 0.0145, client)
    """
    paths = [str(p) for p in paths]
    masses = list(mms) if np.ndim(mms) else [mms] * len(paths)
    if len(masses) != len(paths):
        raise ValueError(f"identify_lot: {len(masses)} moving masses for {len(paths)} records")
    masses = [float(m) for m in masses]
    if client is None:
        return [identify_file(p, m, **options) for p, m in zip(paths, masses)]
    futures = client.map(identify_file, paths, masses, **options)
    return client.gather(futures)


def measure_virtual(driver, seed=1, fs=48000.0, max_seconds=60.0, world="real"):
    """A dynamic measurement of a virtual driver (IEC noise, ramp, protection): the result dict.

    ``world``: ``real`` (as ``coilscope measure --virtual``: typical LOG creep added where the
    set has none, as real suspensions creep) or ``published`` (the set as given). A set with a
    box is refused, as the command line refuses it."""
    return _checked(_c.measure_virtual(_spec(driver), int(seed), float(fs), float(max_seconds), str(world)), "measure_virtual")


def measure_replay(u, i, fs, mms, max_seconds=600.0, mms_sd=0.0):
    """The online estimator on a recording: the result dict. ``mms_sd`` as in :func:`linear`."""
    return _checked(_c.measure_replay(_floats(u, "u"), _floats(i, "i"), float(fs), float(mms), float(max_seconds), float(mms_sd)), "measure_replay")


def distortion(params, freq, volts, output="pressure", temp_rise=0.0):
    """Harmonic distortion of a sine (HD2, HD3, THD, each nonlinearity, and the third-order
    Volterra series of the same set under ``volterra``), the coil ``temp_rise`` K above
    ambient: the dict ``coilscope distortion --json`` prints."""
    return json.loads(_c.distortion(_spec(params), float(freq), float(volts), output, float(temp_rise)))


def quasistatic(driver, points=9, reach=0.8, hold=5.0, order=4, offset="current"):
    """The static and quasi-static point-by-point measurement of a virtual driver (IEC 62458
    10.2/10.3; ``coilscope quasistatic``): the result dict, with a :class:`NotTrustworthy`
    warning when its checks do not trust it. ``offset``: ``current`` (a DC current),
    ``mass`` (an added mass under gravity) or ``pressure`` (needs the set's Sd). The working
    points are under ``quasi_static``."""
    return _checked(_c.quasistatic(_spec(driver), int(points), float(reach), float(hold), int(order), str(offset)), "quasistatic")
