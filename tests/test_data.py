"""Reading measured data: every format round-trips, every bad input is a clear error."""

import h5py
import numpy as np
import pytest
import xarray as xr
from scipy import io as sio

from latentforce.errors import LatentForceError
from latentforce.io.data import Dataset, load_data
from latentforce.io.writers import write_csv

T = 50
DT = 1.0 / 256.0


def _signals():
    rng = np.random.default_rng(0)
    t = np.arange(T) * DT
    return {
        "time": t,
        "acc": rng.standard_normal(T),
        "disp": rng.standard_normal(T) * 1e-7,
        "displacement": np.sin(t),
        "force": np.cos(t),
    }


def _check(ds, sig, columns=("acc", "disp")):
    np.testing.assert_array_equal(ds.time, sig["time"])
    assert ds.dt == pytest.approx(DT, rel=1e-12)
    np.testing.assert_array_equal(ds.values, np.column_stack([sig[c] for c in columns]))
    assert ds.mask.all() and ds.mask.shape == (T, len(columns))
    assert ds.columns == list(columns)
    assert set(ds.truth) == {"displacement", "force"}
    np.testing.assert_array_equal(ds.truth["force"], sig["force"])


def test_csv_round_trip_is_exact(tmp_path):
    sig = _signals()
    path = tmp_path / "data.csv"
    write_csv(path, sig)
    _check(load_data(path, ["acc", "disp"]), sig)


def test_hdf5_round_trip_with_nested_paths(tmp_path):
    sig = _signals()
    path = tmp_path / "data.h5"
    with h5py.File(path, "w") as f:
        f["time"] = sig["time"]
        f["sensors/acc"] = sig["acc"]
        f["sensors/disp"] = sig["disp"].reshape(1, -1)  # a row vector squeezes to 1-D
        f["displacement"] = sig["displacement"]
        f["force"] = sig["force"]
    ds = load_data(path, ["sensors/acc", "sensors/disp"])
    renamed = dict(sig, **{"sensors/acc": sig["acc"], "sensors/disp": sig["disp"]})
    _check(ds, renamed, columns=("sensors/acc", "sensors/disp"))


def test_mat_v5_round_trip(tmp_path):
    sig = _signals()
    path = tmp_path / "data.mat"
    sio.savemat(path, sig)  # stores vectors as 1 x T matrices
    _check(load_data(path, ["acc", "disp"]), sig)


def test_mat_v73_is_read_as_hdf5(tmp_path):
    sig = _signals()
    path = tmp_path / "data73.mat"
    with h5py.File(path, "w") as f:
        for name, arr in sig.items():
            f[name] = arr.reshape(-1, 1)  # MATLAB writes column-major T x 1
        f["#refs#/junk"] = np.zeros(3)
    _check(load_data(path, ["acc", "disp"]), sig)


def test_netcdf_round_trip(tmp_path):
    sig = _signals()
    path = tmp_path / "data.nc"
    ds = xr.Dataset({k: ("sample", v) for k, v in sig.items()})
    ds.to_netcdf(path, engine="h5netcdf")
    _check(load_data(path, ["acc", "disp"]), sig)


def test_sample_rate_replaces_time_column(tmp_path):
    sig = _signals()
    del sig["time"]
    path = tmp_path / "notime.csv"
    write_csv(path, sig)
    ds = load_data(path, ["acc"], sample_rate=256.0)
    np.testing.assert_allclose(ds.time, np.arange(T) / 256.0)
    assert ds.dt == 1 / 256.0


def test_missing_skip_masks_nan_and_inf(tmp_path):
    sig = _signals()
    sig["acc"][[3, 7]] = [np.nan, np.inf]
    path = tmp_path / "gaps.csv"
    write_csv(path, sig)
    ds = load_data(path, ["acc", "disp"], missing="skip")
    assert not ds.mask[3, 0] and not ds.mask[7, 0] and ds.mask[:, 1].all()
    assert np.isnan(ds.values[7, 0])
    assert ds.mask.sum() == 2 * T - 2


def test_from_array_is_the_record_a_file_gives(tmp_path):
    # a record built in memory equals the same numbers written to a file and read back
    sig = _signals()
    sig["acc"][[3, 7]] = [np.nan, np.inf]
    path = tmp_path / "gaps.csv"
    write_csv(path, {k: sig[k] for k in ("time", "acc", "disp")})
    read = load_data(path, ["acc", "disp"], missing="skip")
    built = Dataset.from_array(np.column_stack([sig["acc"], sig["disp"]]), DT, ("acc", "disp"))
    np.testing.assert_allclose(built.time, read.time, rtol=0, atol=1e-15)
    assert built.dt == pytest.approx(read.dt, rel=1e-12)
    np.testing.assert_array_equal(built.values, read.values)
    np.testing.assert_array_equal(built.mask, read.mask)
    assert built.columns == read.columns == ["acc", "disp"] and built.truth == {}
    assert np.isinf(sig["acc"][7])  # the caller's array is not changed


def test_truth_columns_optional_and_suffixed(tmp_path):
    path = tmp_path / "mdof.csv"
    t = np.arange(4) * 0.1
    write_csv(path, {"time": t, "a": t, "displacement_0": t, "displacement_1": 2 * t, "velocity": t})
    ds = load_data(path, ["a"])
    assert set(ds.truth) == {"displacement_0", "displacement_1", "velocity"}
    write_csv(path, {"time": t, "a": t})
    assert load_data(path, ["a"]).truth == {}


# ----- bad inputs ---------------------------------------------------------
def _write_text(tmp_path, text, name="bad.csv"):
    path = tmp_path / name
    path.write_text(text)
    return path


def _raises(path, *fragments, **kwargs):
    columns = kwargs.pop("columns", ["acc"])
    with pytest.raises(LatentForceError) as info:
        load_data(path, columns, **kwargs)
    msg = str(info.value)
    assert path.name in msg
    for frag in fragments:
        assert frag in msg, msg
    assert "\n" not in msg
    return msg


def test_missing_file(tmp_path):
    _raises(tmp_path / "nope.csv", "not found")


def test_empty_file_and_no_rows(tmp_path):
    _raises(_write_text(tmp_path, ""), "empty")
    _raises(_write_text(tmp_path, "\n\n", "blank.csv"), "empty")
    _raises(_write_text(tmp_path, "time,acc\n", "header.csv"), "no data rows")


def test_unknown_column_lists_available(tmp_path):
    path = _write_text(tmp_path, "time,accel\n0,1\n1,2\n")
    msg = _raises(path, "'acc'", "'accel'", "did you mean")
    assert "Available columns" in msg


def test_non_numeric_entry_names_row(tmp_path):
    path = _write_text(tmp_path, "time,acc\n0,1\n1,oops\n2,3\n")
    _raises(path, "'acc'", "'oops'", "row 1", "line 3")


def test_nan_refused_with_hint(tmp_path):
    path = _write_text(tmp_path, "time,acc\n0,1\n1,nan\n2,\n3,4\n")
    _raises(path, "'acc'", "2 NaN/inf", "row 1", 'missing = "skip"')


def test_time_column_problems(tmp_path):
    _raises(_write_text(tmp_path, "t,acc\n0,1\n1,2\n"), "time column 'time' not found", "sample_rate")
    _raises(_write_text(tmp_path, "time,acc\n0,1\n2,2\n1,3\n", "back.csv"), "not increasing", "row 2")
    _raises(
        _write_text(tmp_path, "time,acc\n0,1\n1,2\n2,3\n3.5,4\n", "uneven.csv"),
        "not evenly sampled",
        "row 3",
        "is 1.5 s but the nominal step is 1 s",
    )
    _raises(_write_text(tmp_path, "time,acc\n0,1\nnan,2\n", "nantime.csv"), "'time'", "NaN")


def test_fewer_than_two_samples(tmp_path):
    _raises(_write_text(tmp_path, "time,acc\n0,1\n"), "at least 2")


def test_ragged_csv_row(tmp_path):
    _raises(_write_text(tmp_path, "time,acc\n0,1\n1\n"), "line 3")


def test_a_comment_line_or_another_separator_is_named(tmp_path):
    _raises(_write_text(tmp_path, "# logger export\ntime,acc\n0,1\n1,2\n"), "line 2", "comment or title")
    _raises(_write_text(tmp_path, "time;acc\n0;1\n1;2\n"), "'time;acc'", "separated by commas")
    _raises(_write_text(tmp_path, "time,acc\n0;1\n1;2\n"), "line 2", "other than commas")


def test_a_space_before_a_quoted_header_name_is_not_part_of_it(tmp_path):
    path = _write_text(tmp_path, 'time, "acc"\n0, 1.5\n0.5, 2.5\n', "ok.csv")
    ds = load_data(path, ["acc"])
    np.testing.assert_array_equal(ds.values[:, 0], [1.5, 2.5])


def test_unknown_extension(tmp_path):
    _raises(_write_text(tmp_path, "x", "data.xlsx"), ".xlsx", ".csv", ".nc")


def test_channels_of_different_lengths(tmp_path):
    path = tmp_path / "ragged.h5"
    with h5py.File(path, "w") as f:
        f["time"] = np.arange(5.0)
        f["acc"] = np.arange(4.0)
    _raises(path, "'time'", "4", "5")
    path = tmp_path / "ragged.mat"
    sio.savemat(path, {"time": np.arange(5.0), "acc": np.arange(4.0)})
    _raises(path, "same length")
    path = tmp_path / "ragged.nc"
    xr.Dataset({"time": ("a", np.arange(5.0)), "acc": ("b", np.arange(4.0))}).to_netcdf(path, engine="h5netcdf")
    _raises(path, "same length")


def test_non_numeric_dataset(tmp_path):
    path = tmp_path / "text.h5"
    with h5py.File(path, "w") as f:
        f["time"] = np.arange(3.0)
        f["acc"] = np.array([b"a", b"b", b"c"])
    _raises(path, "'acc'", "non-numeric")


def test_write_csv_refuses_ragged_columns(tmp_path):
    with pytest.raises(ValueError):
        write_csv(tmp_path / "x.csv", {"a": np.zeros(3), "b": np.zeros(4)})
