rule export:
    """The cameras for other tools: nerfstudio transforms.json and a COLMAP text model."""
    wildcard_constraints:
        dataset=id_pattern(DATASETS),
    input:
        rules.poses.output,
    output:
        transforms=f"{RESULTS}/{{dataset}}/export/nerfstudio/transforms.json",
        colmap=directory(f"{RESULTS}/{{dataset}}/export/colmap"),
    params:
        out=f"{RESULTS}/{{dataset}}/export",
        flags=flags("export"),
    log:
        log_file("export"),
    benchmark:
        benchmark_file("export")
    threads: resource("export", "threads")
    resources:
        **rule_resources("export"),
    conda:
        "../../envs/seathru.yaml"
    shell:
        "seathru export --poses {input:q} --out {params.out:q} {params.flags} > {log:q} 2>&1"
