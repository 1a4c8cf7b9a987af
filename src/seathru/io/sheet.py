"""The dataset sheet (``config/datasets.tsv``): tab-separated, a header row, at least a
``dataset`` column (``source``, ``path``, ``options`` as the workflow reads them; ``#`` starts a
comment). The workflow parses it itself (``workflow/rules/common.smk``, no package import);
steps read it here.
"""

from __future__ import annotations

import os
from pathlib import Path

import pandas as pd

from seathru.errors import PipelineError


def read_sheet(path: str | os.PathLike) -> pd.DataFrame:
    """The sheet's rows with a non-empty ``dataset``, every cell as text ("" when empty).

    Raises:
        PipelineError: naming the file when it is missing, not tab-separated or has no
        ``dataset`` column.
    """
    if not Path(path).is_file():
        raise PipelineError(f"{path}: dataset sheet not found")
    try:
        sheet = pd.read_csv(path, sep="\t", dtype=str, keep_default_na=False, comment="#")
    except (pd.errors.ParserError, pd.errors.EmptyDataError) as exc:
        raise PipelineError(f"{path}: cannot be read as a tab-separated sheet ({exc})") from None
    if "dataset" not in sheet.columns:
        raise PipelineError(f"{path}: no 'dataset' column; the sheet is tab-separated with a "
                            f"header row (found columns {list(sheet.columns)})")
    return sheet[sheet["dataset"].str.strip() != ""]
