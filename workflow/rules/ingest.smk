rule ingest:
    """Decode RAW or images to linear radiance, normalise exposure, white balance, masks."""
    wildcard_constraints:
        dataset=id_pattern(DATASETS),
    input:
        ingest_input,
    output:
        directory(f"{RESULTS}/{{dataset}}/ingest"),
    params:
        source=ingest_source_flags,
        flags=flags("ingest"),
    log:
        log_file("ingest"),
    benchmark:
        benchmark_file("ingest")
    threads: resource("ingest", "threads")
    resources:
        **rule_resources("ingest"),
    conda:
        "../../envs/seathru.yaml"
    shell:
        "seathru ingest --input {input:q} --out {output:q} --workers {threads} {params.source} "
        "{params.flags} > {log:q} 2>&1"
