"""JSON Schemas of the files users write, for editors that check and complete TOML
(e.g. Taplo / Even Better TOML: ``#:schema ./docs/schemas/pipeline.schema.json`` on a
file's first line). ``offline-adp schema --write`` regenerates ``docs/schemas/``; a test
keeps the checked-in files equal to the models.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from pydantic import Field, create_model

from offline_adp.algorithms.registry import ALGORITHMS
from offline_adp.config import ConfigModel, json_schema
from offline_adp.pipeline import PipelineFile

#: Where the published schemas live in a checkout.
SCHEMA_DIR = Path(__file__).resolve().parents[1] / "docs" / "schemas"


def fit_config_model() -> type[ConfigModel]:
    """A fit config file (``offline-adp fit --config``): one optional table per algorithm."""
    fields: dict[str, Any] = {name: (e.params_model() | None, Field(None, description=e.summary))
                              for name, e in ALGORITHMS.items()}
    model = create_model("FitConfigFile", __base__=ConfigModel, **fields)
    model.__doc__ = "A fit configuration: the [<algorithm>] table holds the estimator's parameters."
    return model


def schemas() -> dict[str, dict[str, Any]]:
    """name -> JSON Schema of every configuration file type."""
    return {"pipeline": json_schema(PipelineFile), "fit-config": json_schema(fit_config_model())}


def write_schemas(directory: str | Path = SCHEMA_DIR) -> list[Path]:
    """Write every schema as ``NAME.schema.json`` into ``directory``; returns the paths."""
    from offline_adp.data.files import atomic_write_text

    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    out = []
    for name, schema in schemas().items():  # each file atomically: a failed write leaves the previous one
        p = d / f"{name}.schema.json"
        atomic_write_text(p, json.dumps(schema, indent=2, sort_keys=True) + "\n", what="schema file")
        out.append(p)
    return out
