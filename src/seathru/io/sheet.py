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


VARIANT_MARK = "+"      # <dataset>+<variant>, as workflow/rules/common.smk names a sweep's runs
ALL_VARIANTS = "all"


def variant_options(pairs: list[str] | None) -> dict[str, str]:
    """The report's ``--variants NAME=OPTIONS ...`` (the configuration's ``sweep``) as
    name -> options text.

    Raises:
        PipelineError: a pair without ``=``.
    """
    variants = {}
    for pair in pairs or []:
        name, sep, options = pair.partition("=")
        if not sep or not name.strip():
            raise PipelineError(f"--variants {pair!r}: expected NAME=OPTIONS")
        variants[name.strip()] = options.strip()
    return variants


def expand_sweeps(sheet: pd.DataFrame, variants: dict[str, str],
                  source: str | os.PathLike = "the dataset sheet") -> pd.DataFrame:
    """The sheet's rows, each followed by the runs its ``sweep`` column asks for (comma-separated
    variant names, or ``all``), as the workflow runs them: ``dataset`` is ``<dataset>+<variant>``
    and ``options`` the row's options then the variant's. Adds the columns ``base`` (the sheet's
    dataset) and ``variant`` ("" on the sheet's own rows).

    Raises:
        PipelineError: naming the sheet and the dataset when a variant is not in ``variants``.
    """
    rows = []
    for _, row in sheet.iterrows():
        base = {**row.to_dict(), "base": row["dataset"], "variant": ""}
        rows.append(base)
        cell = str(row.get("sweep", "") or "")
        names = list(dict.fromkeys(n.strip() for n in cell.split(",") if n.strip()))
        if ALL_VARIANTS in names:
            names = list(variants)
        for name in names:
            if name not in variants:
                raise PipelineError(f"{source}: dataset {row['dataset']!r}: sweep variant "
                                    f"{name!r} is not given (--variants: "
                                    f"{', '.join(variants) or 'none'})")
            options = "; ".join(part for part in (str(row.get("options", "")).strip(),
                                                  variants[name]) if part)
            rows.append({**base, "dataset": f"{row['dataset']}{VARIANT_MARK}{name}",
                         "options": options, "variant": name})
    columns = [*sheet.columns, "base", "variant"]
    return pd.DataFrame(rows, columns=columns).fillna("")
