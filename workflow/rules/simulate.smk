rule simulate:
    """Synthetic dive scene with known water, cameras and clean images (source: simulated)."""
    wildcard_constraints:
        dataset=id_pattern(DATASETS),
    output:
        directory(f"{RESULTS}/{{dataset}}/simulate"),
    params:
        flags=flags("simulate"),
    log:
        log_file("simulate"),
    benchmark:
        benchmark_file("simulate")
    threads: resource("simulate", "threads")
    resources:
        **rule_resources("simulate"),
    conda:
        "../../envs/seathru.yaml"
    shell:
        "seathru simulate --out {output:q} {params.flags} > {log:q} 2>&1"
