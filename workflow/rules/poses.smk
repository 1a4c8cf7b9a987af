rule poses:
    """Camera intrinsics and poses (COLMAP, or the dataset's own), undistorted linear images."""
    wildcard_constraints:
        dataset=id_pattern(DATASETS),
    input:
        rules.ingest.output,
    output:
        directory(f"{RESULTS}/{{dataset}}/poses"),
    params:
        source=poses_source_flags,
        flags=flags("poses"),
    log:
        log_file("poses"),
    benchmark:
        benchmark_file("poses")
    threads: resource("poses", "threads")
    resources:
        **rule_resources("poses"),
    conda:
        "../../envs/seathru.yaml"
    shell:
        "seathru poses --ingest {input:q} --out {output:q} --threads {threads} {params.source} "
        "{params.flags} > {log:q} 2>&1"
