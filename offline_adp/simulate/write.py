"""Write a simulated dataset in the format ``offline-adp simulate --format`` names."""

from __future__ import annotations

from os import PathLike
from pathlib import Path

from offline_adp.data.dataset import TransitionDataset
from offline_adp.errors import (
    InvalidArgumentError,
    OutputExistsError,
    UnknownNameError,
    ValidationError,
    WriteError,
)

#: ``--format`` choices: a dataset directory, a raw table, or MCAP recordings.
FORMATS = ("dataset", "parquet", "csv", "mcap-json", "mcap-ros2")


def write_simulated(ds: TransitionDataset, out: str | PathLike[str], fmt: str = "dataset", *, overwrite: bool = False,
                    seed: int = 0) -> list[Path]:
    """Write ``ds`` as a dataset directory (checked by the doctor first), a Parquet/CSV
    table (``out`` a file, or a folder that gets ``PROBLEM.FORMAT``) or MCAP files
    (``mcap-json``/``mcap-ros2`` into the folder ``out``); returns the written paths."""
    out = Path(out)
    if fmt not in FORMATS:
        raise UnknownNameError(f"format {fmt!r}: expected one of {list(FORMATS)}")
    if fmt not in ("dataset", "parquet", "csv") and ds.info.action_table.continuous:
        raise InvalidArgumentError(f"--format {fmt}: the MCAP writers log action-table entries, which would drop the "
                                   "exact continuous commands of this dataset; write --format dataset, parquet or csv")
    if fmt == "dataset":
        from offline_adp.data.validate import validate

        report = validate(ds)
        if not report.ok:  # a simulator bug, never user input
            raise ValidationError("simulated data failed the doctor:\n" + report.to_text(), report)
        ds.save(out, overwrite=overwrite)
        return [out]
    if fmt in ("parquet", "csv"):
        from offline_adp.simulate.raw import write_raw

        if out.suffix == "":
            out = out / f"{ds.info.problem}.{fmt}"
        if out.is_dir():
            raise WriteError(f"{out} is a directory; name the {fmt} file to write (or a folder without a suffix)")
        from offline_adp.data.files import locked_directory

        with locked_directory(out, what=f"{fmt} table"):  # the table and its spec: one writer at a time
            if out.exists() and not overwrite:
                raise OutputExistsError(f"{out} already exists; pass --overwrite to replace it")
            return list(write_raw(ds, out, fmt=fmt))
    from offline_adp.simulate.mcap_writer import write_mcap

    if out.exists() and not out.is_dir():
        raise WriteError(f"{out} is a file; MCAP recordings are written into a folder (name one)")
    from offline_adp.data.files import locked_directory

    with locked_directory(out, what="MCAP folder"):
        # the temporaries of a write killed before (kill -9): nothing else writes here while we hold the lock,
        # and they neither make the folder "not empty" nor stay behind
        stale = sorted(out.glob(".*.mcap.tmp")) if out.is_dir() else []
        if out.exists() and any(p not in stale for p in out.iterdir()) and not overwrite:
            raise OutputExistsError(f"{out} is not empty; pass --overwrite to write into it")
        for p in stale:
            p.unlink()
        return list(write_mcap(ds, out, encoding=fmt.split("-")[1], seed=seed))
