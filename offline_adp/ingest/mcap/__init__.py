"""MCAP logs -> dataset (the only module that imports ``mcap``).

Reading: a record-level scan of each file in file order (no index or summary needed).
A chunk that fails to decompress or to match its CRC is skipped and reported ("lost
chunk at offset Y"), and reading continues with the next record; a file cut short
(crash during recording) keeps every complete record before the cut and reports
"recovered N messages of file X, lost from offset Y". Per ``on_error`` the damage fails
the ingestion or is reported and the episodes it touched are left out.

Assembly streams: messages go into per-stream buffers; once every stream has moved
``reorder_window`` seconds past a step, the step is aligned (``nearest``, ``previous``,
``linear`` with ``max_age``), joined to the episode being assembled, and the buffers are
pruned. Memory is bounded by the episode being assembled plus the reorder window, not
by the file. Time sources that go backwards (``log_time`` restarting between
concatenated episodes) start a new *epoch*: an episode boundary.

Spec (TOML), see ``docs/ingestion-spec.md``::

    [sources]  files (globs, relative to the spec), split_recordings
    [clock]    topic | rate_hz (+ reference), time, reorder_window
    [episodes] topic, id_field, event_field, terminated_field, source_field, gap,
               restart, per_file, end_when, terminal_when
    [[streams]] topic, role, time, align, max_age, missing, fill, fields = {name = "path"}
    [action]   topic, field, time, align, max_age, + the Parquet spec's action keys
    [cost]     terms = [{field, op, weight, at}] | field | reward, terminal_cost
    [source]   value | by_file = {glob = label}
    [hints]    gamma, horizon
"""

from offline_adp.ingest.mcap.align import _align
from offline_adp.ingest.mcap.build import ingest_mcap
from offline_adp.ingest.mcap.decode import (
           JsonDecoderFactory,
           decoder_factories,
           field_paths,
           get_path,
           to_ns,
)
from offline_adp.ingest.mcap.info import mcap_info
from offline_adp.ingest.mcap.scan import damage_text, scan_records
from offline_adp.ingest.mcap.sources import resolve_sources
from offline_adp.ingest.mcap.spec import (
           Condition,
           McapSpec,
           StreamSpec,
           load_mcap_spec,
           parse_mcap_spec,
)

__all__ = ["Condition", "JsonDecoderFactory", "McapSpec", "StreamSpec", "_align", "damage_text", "decoder_factories",
           "field_paths", "get_path", "ingest_mcap", "load_mcap_spec", "mcap_info", "parse_mcap_spec",
           "resolve_sources", "scan_records", "to_ns"]
