rule evaluate:
    """PSNR / SSIM on held-out views; against the truth for simulated datasets."""
    input:
        unpack(evaluate_inputs),
    output:
        metrics=report(
            f"{RESULTS}/{{dataset}}/evaluate/metrics.csv",
            caption="../report/metrics.rst",
            category="Per-dataset metrics",
            labels={"dataset": "{dataset}"},
        ),
        summary=f"{RESULTS}/{{dataset}}/evaluate/summary.json",
        frontier=f"{RESULTS}/{{dataset}}/evaluate/frontier.csv",
    params:
        out=f"{RESULTS}/{{dataset}}/evaluate",
        train_dir=f"{RESULTS}/{{dataset}}/train",
        truth=truth_flag,
        flags=flags("evaluate"),
    log:
        log_file("evaluate"),
    benchmark:
        benchmark_file("evaluate")
    threads: resource("evaluate", "threads")
    resources:
        **rule_resources("evaluate"),
    conda:
        "../../envs/seathru.yaml"
    shell:
        "seathru evaluate --renders {input.renders:q} --cameras {input.poses:q}/cameras.json "
        "--train-dir {params.train_dir:q} {params.truth} --out {params.out:q} --threads {threads} "
        "{params.flags} "
        "> {log:q} 2>&1"
