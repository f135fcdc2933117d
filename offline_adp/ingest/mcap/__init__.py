"""MCAP logs (and ROS bags) -> dataset: the only package that imports ``mcap``.

One job per module:

- ``scan``: record-level scan of a file in file order (no index or summary needed),
  recovery from damage (lost chunks, a cut), bounds on untrusted lengths and counts;
- ``decode``: decoders (JSON, ROS 2 CDR, protobuf), field paths, message times;
- ``info``: ``mcap-info`` (every readable file described, damage shown);
- ``spec``: the ingestion spec (TOML) as frozen dataclasses, checked on load;
- ``sources``: inputs -> recordings (globs, split recordings, rosbag2 bag directories);
- ``rosbags_source``: ROS 1 ``.bag`` and rosbag2 SQLite bags through ``rosbags``;
- ``bagmeta``: a bag's ``metadata.yaml`` as untrusted input (size cap, no YAML aliases,
  files confined to the bag, each once);
- ``ros1scan``: record scan of a ROS 1 bag without its index (a bag cut short);
- ``records``: the typed records passed between the parts;
- ``align``: one stream's values at the step times;
- ``buffers``: one stream's messages in one epoch, sorted on demand, pruned behind the watermark;
- ``assembler``: the streaming assembler (epochs from the file order, watermark,
  bounded buffers, steps);
- ``damage``: the assembler's damage accounting (epochs and steps the lost chunks may have
  held, episodes whose start event was lost);
- ``episodes``: cutting steps into episodes (events, gaps, conditions, drops) and reading
  the episode events' fields;
- ``build``: ``ingest_mcap``: recordings -> dataset, quarantine, summary; ``assemble`` runs
  the assembler on in-memory messages.

Memory is bounded by the episode being assembled plus the reorder window, not by the
file. The epoch rules, damage accounting and spec keys are in ``docs/ingestion-spec.md``::

    [sources]  files (globs, relative to the spec), split_recordings
    [clock]    topic | rate_hz (+ reference), time, reorder_window
    [episodes] topic, id_field, event_field, terminated_field, source_field, gap,
               restart, per_file, end_when, terminal_when
    [[streams]] topic, role, time, align, max_age, missing, fill, units, fields = {name = "path"}
    [action]   topic, field | fields, time, align, max_age, missing, fill, + action table keys
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
