"""Dataset folders never reach outside the dataset: symbolic links for products/, records/,
products/tNNNNNNN or the lock are refused with the path named and their targets untouched; --force
and reruns remove only the dataset's own files.  Real folders in tmp_path, no Dask."""
import json
import os

import pytest

from slicersim.errors import DatasetError
from slicersim.io.dataset import Dataset, target_key

SPEC = {"seed": 1, "name": "t"}


def _dataset(tmp_path):
    ds = Dataset(tmp_path / "ds")
    with ds:
        ds.initialise("seed = 1\n", SPEC, {"slicersim": "x"})
    return ds


def _done(ds, tid, files=("spectrum.h5",)):
    """A target with products and a done record naming them."""
    pdir = ds.target_dir(tid, make=True)
    products = {}
    for name in files:
        with open(os.path.join(pdir, name), "wb") as fh:
            fh.write(b"product")
        products[name[:-3]] = {"file": name, "bytes": 7, "sha256": "0" * 64}
    ds.write_record(tid, {"target_id": tid, "status": "done", "products": products})


def _victim(tmp_path):
    """An outside folder holding a file that must survive: (folder, file, its bytes)."""
    outside = tmp_path / "outside"
    outside.mkdir()
    victim = outside / "spectrum.h5"
    victim.write_bytes(b"not yours")
    (outside / "precious.txt").write_bytes(b"keep")
    return outside


def _untouched(outside):
    assert sorted(os.listdir(outside)) == ["precious.txt", "spectrum.h5"]
    assert (outside / "spectrum.h5").read_bytes() == b"not yours" and (outside / "precious.txt").read_bytes() == b"keep"


def test_symlinked_target_folder_is_refused_and_its_target_untouched(tmp_path):
    """Adversarial finding: products/tNNNNNNN as a link → clean_target deleted every file of the link's target."""
    ds = _dataset(tmp_path)
    outside = _victim(tmp_path)
    os.symlink(outside, ds.product_dir(3))
    with pytest.raises(DatasetError, match=f"{target_key(3)} is a symbolic link"):
        ds.clean_target(3)
    with pytest.raises(DatasetError, match=f"{target_key(3)} is a symbolic link"):
        ds.target_dir(3, make=True)
    with pytest.raises(DatasetError, match=f"{target_key(3)} is a symbolic link"):
        with ds:
            ds.initialise("seed = 1\n", SPEC, {"slicersim": "x"})          # a resume refuses it up front
    with pytest.raises(DatasetError, match=f"{target_key(3)} is a symbolic link"):
        ds.discard()
    _untouched(outside)


def test_failed_target_in_a_symlinked_folder_removes_nothing(tmp_path):
    from slicersim.campaign.products import mark_failed
    ds = _dataset(tmp_path)
    outside = _victim(tmp_path)
    os.symlink(outside, ds.product_dir(4))
    record = {"target_id": 4}
    mark_failed(ds, 4, record, RuntimeError("boom"))
    assert record["status"] == "failed"
    _untouched(outside)


@pytest.mark.parametrize("sub", ["records", "products"])
def test_symlinked_records_or_products_are_refused(tmp_path, sub):
    """Adversarial finding: records/ as a link → records written outside the dataset."""
    ds = Dataset(tmp_path / "ds")
    outside = _victim(tmp_path)
    os.makedirs(ds.path)
    os.symlink(outside, ds.file(sub))
    with pytest.raises(DatasetError, match=f"ds/{sub} is a symbolic link"):
        with ds:
            ds.initialise("seed = 1\n", SPEC, {"slicersim": "x"})
    with pytest.raises(DatasetError, match=f"ds/{sub} is a symbolic link"):
        if sub == "records":
            ds.write_record(1, {"target_id": 1, "status": "failed"})
        else:
            ds.target_dir(1, make=True)
    with pytest.raises(DatasetError, match=f"ds/{sub} is a symbolic link"):
        ds.discard()
    _untouched(outside)


def test_a_file_where_a_folder_belongs_is_refused(tmp_path):
    ds = _dataset(tmp_path)
    os.rmdir(ds.file("records"))
    (tmp_path / "ds" / "records").write_bytes(b"")
    with pytest.raises(DatasetError, match="ds/records is not a folder"):
        ds.write_record(1, {"target_id": 1})


def test_symlinked_lock_is_refused_and_its_target_not_truncated(tmp_path):
    ds = Dataset(tmp_path / "ds")
    os.makedirs(ds.path)
    outside = _victim(tmp_path)
    os.symlink(outside / "precious.txt", ds.file(".lock"))
    with pytest.raises(DatasetError, match=r"\.lock"):
        ds.lock()
    _untouched(outside)


def test_force_on_a_folder_with_an_unrelated_products_folder_deletes_nothing(tmp_path):
    """Adversarial finding: --force on a folder holding an unrelated products/ deleted it."""
    folder = tmp_path / "work"
    (folder / "products" / "mine").mkdir(parents=True)
    (folder / "products" / "notes.txt").write_bytes(b"mine")
    (folder / "products" / "mine" / "data.h5").write_bytes(b"mine")
    with pytest.raises(DatasetError, match="is not a slicersim dataset"):
        Dataset.check_path(folder, force=True)
    assert (folder / "products" / "notes.txt").read_bytes() == b"mine"
    assert (folder / "products" / "mine" / "data.h5").read_bytes() == b"mine"


def test_discard_removes_only_the_datasets_own_files(tmp_path):
    """--force (another spec) removes the files the records name and the dataset's own names; nothing else."""
    ds = _dataset(tmp_path)
    _done(ds, 1, ("spectrum.h5", "cube.h5"))
    _done(ds, 2)
    foreign = [os.path.join(ds.product_dir(1), "README"), os.path.join(ds.file("products"), "notes.txt"),
               os.path.join(ds.file("records"), "mine.json")]
    for path in foreign:
        with open(path, "wb") as fh:
            fh.write(b"keep")
    os.makedirs(os.path.join(ds.file("products"), "t0000009", "sub"))        # a folder is never removed
    ds.discard()
    left = sorted(os.path.relpath(os.path.join(d, f), ds.path) for d, _, fs in os.walk(ds.path) for f in fs)
    assert left == [".lock", "products/notes.txt", "products/t0000001/README", "records/mine.json"]
    assert os.path.isdir(os.path.join(ds.file("products"), "t0000009", "sub"))
    for path in foreign:
        with open(path, "rb") as fh:
            assert fh.read() == b"keep"


def test_rerun_of_a_target_removes_only_its_own_files(tmp_path):
    ds = _dataset(tmp_path)
    _done(ds, 5)
    keep = os.path.join(ds.product_dir(5), "notes.txt")
    with open(keep, "wb") as fh:
        fh.write(b"keep")
    ds.clean_target(5)
    assert os.listdir(ds.product_dir(5)) == ["notes.txt"]
    assert not os.path.exists(ds.record_path(5))


def test_product_that_is_not_a_regular_file_is_not_done(tmp_path):
    """A FIFO in place of a product is never read (it would block): the target is recomputed."""
    ds = _dataset(tmp_path)
    _done(ds, 6)
    path = os.path.join(ds.product_dir(6), "spectrum.h5")
    os.remove(path)
    os.mkfifo(path)
    state = ds.state([6], deep=True)[6]
    assert state[0] == "missing" and "not a regular file" in state[2]


def test_remove_new_leaves_nothing_of_a_failed_new_dataset(tmp_path):
    """A run that fails before any target is recorded (e.g. a full disk) leaves no empty dataset folder."""
    ds = _dataset(tmp_path)
    ds.remove_new()
    assert not os.path.lexists(ds.path)
    ds = _dataset(tmp_path)
    _done(ds, 1)                                    # something computed: kept
    ds.remove_new()
    assert json.loads(open(ds.record_path(1)).read())["status"] == "done"


def test_product_file_bytes_do_not_depend_on_when_a_handle_is_released(tmp_path, monkeypatch):
    """A Dask worker's profiler can hold a frame (and so a dataset handle) a moment longer: a
    chunk written when its handle closes would then land elsewhere, giving the same data in a
    file with other bytes (campaign products compared by sha256 differed between runs)."""
    import h5py
    import numpy as np
    from slicersim.io.dataset import ProductFile
    data = {name: np.arange(510.0) * (i + 1) for i, name in enumerate(("lbda", "flambda", "signal", "noisy"))}
    create = h5py.Group.create_dataset

    def write(path, hold):
        held = []

        def create_and_hold(group, name, **kw):
            dset = create(group, name, **kw)
            if name == hold:
                held.append(dset)
            return dset
        monkeypatch.setattr(h5py.Group, "create_dataset", create_and_hold)
        with ProductFile(path, overwrite=True) as f:
            f.set_attrs({"target_id": 1})
            for name, arr in data.items():
                f.write(name, arr, {"unit": "adu"})
                if name == "signal":
                    held.clear()              # released two writes later
        monkeypatch.setattr(h5py.Group, "create_dataset", create)
        return (tmp_path / path).read_bytes()

    monkeypatch.chdir(tmp_path)
    plain, held = write("plain.h5", None), write("held.h5", "flambda")
    assert plain == held
    with h5py.File(tmp_path / "held.h5", "r") as f:
        assert all(f[name].fletcher32 and np.array_equal(f[name][...], arr) for name, arr in data.items())


def test_a_full_disk_while_taking_the_lock_names_the_lock_file(tmp_path, monkeypatch):
    """`campaign run` on a full disk said only "[Errno 28] No space left on device"."""
    import errno

    from slicersim.io import dataset as dataset_module

    def full(fd, data, offset):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    monkeypatch.setattr(dataset_module.os, "pwrite", full)
    with pytest.raises(DatasetError, match=r"cannot write the dataset lock .*ds/\.lock \(\[Errno 28\] No space"):
        Dataset(tmp_path / "ds").lock()
