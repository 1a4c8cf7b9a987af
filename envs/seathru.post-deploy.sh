#!/usr/bin/env bash
# Snakemake runs this after it creates the conda environment of envs/seathru.yaml, inside that
# environment, from a copy at .snakemake/conda/<hash>.post-deploy.sh in the working directory:
# it installs this checkout's package (the `seathru` command) into the environment, by the
# checkout's absolute path. The pinned dependencies come from envs/seathru.yaml (--no-deps).
#
# The checkout is, in this order: $SEATHRU_SOURCE_DIR (set by workflow/rules/common.smk to the
# checkout the Snakefile was read from), else the first folder above this script's copy or
# above the working directory whose pyproject.toml names the project seathru-pipeline.
# The install is editable, as in the .venv that `make` builds: code changes need no new env.
set -euo pipefail

is_checkout() {
    [ -f "$1/pyproject.toml" ] && grep -qE '^name *= *"seathru-pipeline"' "$1/pyproject.toml"
}

find_up() {  # folder -> the first checkout at or above it
    local dir
    dir=$(cd "$1" 2>/dev/null && pwd -P) || return 1
    while :; do
        if is_checkout "$dir"; then
            echo "$dir"
            return 0
        fi
        [ "$dir" = / ] && return 1
        dir=$(dirname "$dir")
    done
}

if [ -n "${SEATHRU_SOURCE_DIR:-}" ]; then
    is_checkout "$SEATHRU_SOURCE_DIR" || {
        echo "seathru post-deploy: SEATHRU_SOURCE_DIR=$SEATHRU_SOURCE_DIR is not a seathru-pipeline" \
             "checkout (no pyproject.toml naming it)" >&2
        exit 1
    }
    source_dir=$(cd "$SEATHRU_SOURCE_DIR" && pwd -P)
elif ! source_dir=$(find_up "$(dirname "$0")") && ! source_dir=$(find_up "$PWD"); then
    echo "seathru post-deploy: cannot find the seathru-pipeline checkout above $0 or $PWD;" \
         "set SEATHRU_SOURCE_DIR to its folder" >&2
    exit 1
fi

echo "seathru post-deploy: installing $source_dir"
python -m pip install --no-deps --editable "$source_dir"
