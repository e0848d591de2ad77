"""Unit labels of netCDF and HDF5 files (a variable's ``units`` attribute).

A channel labelled in g, mm or UDUNITS syntax ("m s-2") is read in SI as a
vendor file's label is; the time column in seconds and the truth columns in
SI by their labels; a label that does not fit is an error naming the file,
the column and the label (a truth column's is left out with a note instead).
The reference for each number is the same data written plainly in SI, or the
factor by hand.
"""

import h5py
import numpy as np
import pytest
import xarray as xr

import latentforce  # noqa: F401  (float64)
from latentforce.errors import LatentForceError
from latentforce.io.channels import ChannelSpec, load_channels
from latentforce.io.data import read_table
from latentforce.io.units import unit_scale
from latentforce.io.writers import write_data

G = 9.80665
T = 50
DT = 0.01


def _signals():
    rng = np.random.default_rng(4)
    return 0.3 * rng.standard_normal(T), 2.0 * rng.standard_normal(T), rng.standard_normal(T)


@pytest.mark.parametrize(
    "label, si, scale",
    [
        ("m s-2", "m/s^2", 1.0),
        ("m/s2", "m/s^2", 1.0),
        ("m.s-2", "m/s^2", 1.0),
        ("m.s^-2", "m/s^2", 1.0),
        ("mm s-2", "m/s^2", 1e-3),
        ("mm s-1", "m/s", 1e-3),
        ("cm/s2", "m/s^2", 1e-2),
        ("kg m s-2", "N", 1.0),
        ("um", "m", 1e-6),
        ("g", "m/s^2", G),
    ],
)
def test_udunits_labels_read_as_their_unit(label, si, scale):
    assert unit_scale(label, si) == pytest.approx(scale, rel=1e-14)


def test_udunits_labels_of_another_dimension_are_refused():
    with pytest.raises(ValueError, match="dimension"):
        unit_scale("mm s-1", "m/s^2")  # a velocity, not an acceleration
    with pytest.raises(ValueError):
        unit_scale("m s-2x", "m/s^2")


def _write_nc(path, time, columns, units):
    xr.Dataset(
        {n: ("time", v, {"units": units[n]} if n in units else {}) for n, v in columns.items()},
        coords={"time": ("time", time, {"units": units["time"]} if "time" in units else {})},
    ).to_netcdf(path, engine="h5netcdf")


def _write_h5(path, time, columns, units):
    with h5py.File(path, "w") as f:
        for n, v in {"time": time, **columns}.items():
            f.create_dataset(n, data=v)
            if n in units:
                # h5py writes str attributes as variable-length strings; MATLAB and others as bytes
                f[n].attrs["units"] = np.bytes_(units[n]) if n == "disp" else units[n]


@pytest.mark.parametrize("writer", [_write_nc, _write_h5], ids=["nc", "h5"])
def test_labelled_channels_time_and_truth_are_read_in_si(tmp_path, writer):
    acc, disp, force = _signals()
    time = 1000.0 * DT * np.arange(T)  # in ms
    path = tmp_path / f"rec.{'nc' if writer is _write_nc else 'h5'}"
    labels = {"time": "ms", "acc": "g", "disp": "mm", "force": "kN"}
    writer(path, time, {"acc": acc, "disp": disp, "force": force}, labels)
    specs = [ChannelSpec("acc", "acceleration", label="[[sensors]][0]"), ChannelSpec("disp", "displacement")]
    ds = load_channels(specs, path)
    np.testing.assert_allclose(ds.values[:, 0], G * acc, rtol=1e-15)
    np.testing.assert_allclose(ds.values[:, 1], 1e-3 * disp, rtol=1e-15)
    assert ds.dt == pytest.approx(DT, rel=1e-12)
    np.testing.assert_allclose(ds.time, DT * np.arange(T), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(ds.truth["force"], 1e3 * force, rtol=1e-15)
    assert {c: (u.unit, u.scale, u.source) for c, u in ds.units.items()} == {
        "acc": ("g", G, "file"),
        "disp": ("mm", pytest.approx(1e-3, rel=1e-14), "file"),
    }
    # the sensor's unit key overrides the label (here: the numbers are SI after all)
    over = load_channels([ChannelSpec("acc", "acceleration", unit="m/s^2")], path)
    np.testing.assert_array_equal(over.values[:, 0], acc)
    # read_table: the numbers as the file holds them, with their labels
    raw, found = read_table(path, ["acc", "disp"])
    np.testing.assert_array_equal(raw.values[:, 0], acc)
    assert found == {"acc": "g", "disp": "mm"}


def test_unlabelled_and_none_labels_are_taken_as_si(tmp_path):
    acc, disp, _ = _signals()
    path = tmp_path / "rec.nc"
    _write_nc(path, DT * np.arange(T), {"acc": acc, "disp": disp}, {"disp": "none"})
    ds = load_channels([ChannelSpec("acc", "acceleration"), ChannelSpec("disp", "displacement")], path)
    np.testing.assert_array_equal(ds.values, np.column_stack([acc, disp]))
    assert {u.source for u in ds.units.values()} == {"assumed"}


def test_cf_time_labels(tmp_path):
    """A CF "seconds since" time: decoded by xarray in netCDF, read as seconds in HDF5."""
    acc, _, _ = _signals()
    for writer, name in ((_write_nc, "rec.nc"), (_write_h5, "rec.h5")):
        path = tmp_path / name
        writer(path, 5.0 + DT * np.arange(T), {"acc": acc}, {"time": "seconds since 2024-01-01 00:00:00"})
        ds = load_channels([ChannelSpec("acc", "acceleration")], path)
        assert ds.dt == pytest.approx(DT, rel=1e-9), name
        np.testing.assert_array_equal(ds.values[:, 0], acc)


def _raises(fn, *parts):
    with pytest.raises(LatentForceError) as info:
        fn()
    text = str(info.value)
    for part in parts:
        assert part in text, (part, text)


def test_labels_that_do_not_fit_name_the_file_column_and_label(tmp_path):
    acc, disp, force = _signals()
    path = tmp_path / "bad.nc"
    _write_nc(path, DT * np.arange(T), {"acc": acc}, {"acc": "V"})
    _raises(
        lambda: load_channels([ChannelSpec("acc", "acceleration", label="[[sensors]][0]")], path),
        "sensor [[sensors]][0] (column 'acc')",
        "'V'",
        "bad.nc",
        "does not fit quantity 'acceleration'",
        "unit key",
    )
    _write_nc(path, DT * np.arange(T), {"acc": acc}, {"acc": "blorps"})
    _raises(lambda: load_channels([ChannelSpec("acc", "acceleration")], path), "'blorps'", "pint", "unit key")
    _write_nc(path, DT * np.arange(T), {"acc": acc}, {"time": "m"})
    _raises(lambda: load_channels([ChannelSpec("acc", "acceleration")], path), "bad.nc", "'time'", "'m'", "'s'")
    # a truth column (a variable merely named velocity) whose label does not fit is left out, with a note
    _write_nc(path, DT * np.arange(T), {"acc": acc, "velocity": disp, "force": disp}, {"velocity": "mm"})
    for ds in (load_channels([ChannelSpec("acc", "acceleration")], path), read_table(path, ["acc"])[0]):
        assert set(ds.truth) == {"force"} and len(ds.notes) == 1
        for fragment in ("bad.nc", "'velocity'", "'mm'", "'m/s'", "left out", "coverage and NMSE"):
            assert fragment in ds.notes[0], ds.notes


@pytest.mark.parametrize("ext", ["nc", "h5"])
def test_write_data_labels_read_back(tmp_path, ext):
    """write_data's labels (what ``simulate`` writes) are what the reader finds."""
    acc, disp, force = _signals()
    path = tmp_path / f"sim.{ext}"
    write_data(
        path,
        {"time": DT * np.arange(T), "acc": acc, "disp": disp, "force": force},
        {"time": "s", "acc": "g", "disp": "m", "force": "N"},
    )
    ds, labels = read_table(path, ["acc", "disp"])
    assert labels == {"acc": "g", "disp": "m"}
    np.testing.assert_array_equal(ds.truth["force"], force)
    si = load_channels([ChannelSpec("acc", "acceleration"), ChannelSpec("disp", "displacement")], path)
    np.testing.assert_allclose(si.values[:, 0], G * acc, rtol=1e-15)


def test_simulate_labels_its_netcdf_and_estimate_reads_them(tmp_path, monkeypatch):
    """simulate --out x.nc with an accelerometer in g: estimate without the unit key reads the same data."""
    from typer.testing import CliRunner

    from latentforce.cli import app
    from latentforce.io.channels import load_problem_data
    from latentforce.io.config import load_config

    monkeypatch.chdir(tmp_path)
    body = (
        '[system]\ntype = "linear"\nm = 1.0\nc = 0.8\nk = 40.0\n'
        '[force]\nkernel = "matern32"\nvariance = 4.0\nlengthscale = 0.1\n'
        '[[sensors]]\ncolumn = "acc"\nquantity = "acceleration"\nnoise_std = 0.01\n{unit}'
        '[[sensors]]\ncolumn = "force"\nquantity = "force"\nnoise_std = 0.01\nunit = "kN"\n'
        '[inference]\nmethod = "kalman"\n[data]\npath = "sim.nc"\n'
    )
    (tmp_path / "with.toml").write_text(body.format(unit='unit = "g"\n'))
    (tmp_path / "without.toml").write_text(body.format(unit=""))
    result = CliRunner().invoke(app, ["simulate", "with.toml", "--out", "sim.nc", "--duration", "1"])
    assert result.exit_code == 0, result.output
    with xr.open_dataset(tmp_path / "sim.nc", decode_timedelta=False) as f:
        attrs = {n: f[n].attrs.get("units") for n in f.variables}
    assert attrs == {"time": "s", "acc": "g", "force": "kN", "displacement": "m", "velocity": "m/s"}
    a = load_problem_data(load_config(tmp_path / "with.toml"))
    b = load_problem_data(load_config(tmp_path / "without.toml"))
    np.testing.assert_array_equal(a.values, b.values)
    assert b.units["acc"].source == "file" and b.units["acc"].scale == G


def test_a_unit_key_that_overrides_a_label_of_another_scale_is_named():
    """The sensor's unit key wins over the file's label; where the label reads as a different unit of
    the same quantity (one of the two is wrong), the channel unit keeps it and the run warns."""
    from latentforce.io.units import override_warning, resolve_unit

    clash = resolve_unit("acceleration", "m/s^2", "g", who="s", where="f")
    assert (clash.scale, clash.source, clash.file_label) == (1.0, "sensor", "g")
    for label in ("m s-2", "m/s^2", "NONE", "V", "blorps", None):  # same scale, none, or no unit that fits
        assert resolve_unit("acceleration", "m/s^2", label, who="s", where="f").file_label is None, label
    text = override_warning({"acc": clash, "disp": resolve_unit("displacement", "mm", "mm", who="s", where="f")})
    assert "column 'acc'" in text and "'g'" in text and "9.807" in text and "disp" not in text
    assert override_warning({"disp": resolve_unit("displacement", None, "mm", who="s", where="f")}) is None


def test_estimate_warns_of_the_override_and_records_the_label(tmp_path):
    import json

    from latentforce import estimate
    from latentforce.io.channels import channel_units, load_problem_data
    from latentforce.io.config import config_from_dict

    acc, disp, force = _signals()
    columns = {"acc": acc, "force": force, "displacement": disp}
    _write_nc(tmp_path / "rec.nc", DT * np.arange(T), columns, {"acc": "g", "displacement": "V"})
    config = {
        "data": {"path": "rec.nc"},
        "system": {"type": "linear", "m": 1.0, "c": 0.8, "k": 40.0},
        "force": {"kernel": "matern32", "variance": 4.0, "lengthscale": 0.1},
        "sensors": [{"column": "acc", "quantity": "acceleration", "noise_std": 0.01, "unit": "m/s^2"}],
        "inference": {"method": "kalman"},
    }
    problem = config_from_dict(config, source="lf.toml", base_dir=tmp_path)
    dataset = load_problem_data(problem)
    np.testing.assert_array_equal(dataset.values[:, 0], acc)  # the key's unit, not the label's
    result, _ = estimate.run(problem, dataset)
    assert any("overrides the data file's own unit label" in w for w in result.diagnostics["warnings"])
    # the displacement truth in volts is left out of the scoring, and the run says so
    assert "displacement" not in result.truth and "force" in result.truth
    assert any("column 'displacement'" in w and "left out" in w for w in result.diagnostics["warnings"])
    assert json.loads(json.dumps(channel_units(dataset)))["acc"]["file_label"] == "g"


def test_vendor_spellings_g_s_and_engineering_units():
    """ "g's" is g (pint reads g times seconds); "EU" names no unit (pint: the enzyme unit)."""
    from latentforce.io.units import resolve_unit

    assert resolve_unit("acceleration", None, "g's", who="s", where="f").scale == G
    with pytest.raises(LatentForceError, match="engineering units.*unit key"):
        resolve_unit("acceleration", None, "EU", who="s", where="f")


def test_netcdf3_files_attribute_spellings_and_coarse_time_stamps(tmp_path):
    """A netCDF-3 (classic) file reads (through scipy); "Units"/"unit" attributes are labels; time
    stamps stored in float32, or as absolute epoch seconds, are even to their storage resolution and
    give the mean step; a sample_rate is checked against the time column in seconds."""
    acc, disp, _ = _signals()
    path = tmp_path / "classic.nc"
    xr.Dataset(
        {"acc": ("time", acc, {"Units": "g"}), "disp": ("time", disp, {"unit": "mm"})},
        coords={"time": ("time", DT * np.arange(T))},
    ).to_netcdf(path, engine="scipy")
    ds = load_channels([ChannelSpec("acc", "acceleration"), ChannelSpec("disp", "displacement")], path)
    np.testing.assert_allclose(ds.values, np.column_stack([G * acc, 1e-3 * disp]), rtol=1e-15)
    for name, stamps in (("f32.h5", (DT * np.arange(T)).astype(np.float32)), ("epoch.h5", 1.7e9 + DT * np.arange(T))):
        _write_h5(tmp_path / name, stamps, {"acc": acc}, {})
        got = load_channels([ChannelSpec("acc", "acceleration")], tmp_path / name)
        assert got.dt == pytest.approx(DT, rel=1e-7), name
    with h5py.File(tmp_path / "bad.h5", "w") as f:  # a real jitter is still refused
        f["time"], f["acc"] = DT * np.arange(T) + 1e-4 * (np.arange(T) == 7), acc
    with pytest.raises(LatentForceError, match="not evenly sampled"):
        load_channels([ChannelSpec("acc", "acceleration")], tmp_path / "bad.h5")
    _write_nc(tmp_path / "ms.nc", 1e3 * DT * np.arange(T), {"acc": acc}, {"time": "ms"})
    rate = load_channels([ChannelSpec("acc", "acceleration")], tmp_path / "ms.nc", sample_rate=1 / DT)
    assert rate.dt == pytest.approx(DT)
    with pytest.raises(LatentForceError, match="sample_rate"):
        load_channels([ChannelSpec("acc", "acceleration")], tmp_path / "ms.nc", sample_rate=10 / DT)
