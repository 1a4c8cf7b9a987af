rule render:
    """Held-out views and a camera path: full, restored, depth, backscatter, direct; videos."""
    input:
        model=rules.train.output.model,
        poses=poses_input,
    output:
        directory(f"{RESULTS}/{{dataset}}/render"),
    params:
        flags=flags("render"),
    log:
        log_file("render"),
    benchmark:
        benchmark_file("render")
    threads: resource("render", "threads")
    resources:
        **rule_resources("render"),
    conda:
        "../../envs/seathru.yaml"
    shell:
        "seathru render --model {input.model:q} --cameras {input.poses:q}/cameras.json "
        "--out {output:q} --threads {threads} {params.flags} > {log:q} 2>&1"
