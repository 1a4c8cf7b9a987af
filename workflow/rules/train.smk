rule train:
    """Fit the SeaThru-NeRF model; resumes from results/<dataset>/checkpoints/ after a kill."""
    input:
        poses_input,
    output:
        model=f"{RESULTS}/{{dataset}}/train/model.pt",
        water=f"{RESULTS}/{{dataset}}/train/water.json",
        log_csv=f"{RESULTS}/{{dataset}}/train/train_log.csv",
        selection=f"{RESULTS}/{{dataset}}/train/selection.json",
    params:
        out=f"{RESULTS}/{{dataset}}/train",
        checkpoints=f"{RESULTS}/{{dataset}}/checkpoints",
        flags=flags("train"),
    log:
        log_file("train"),
    benchmark:
        benchmark_file("train")
    threads: resource("train", "threads")
    resources:
        **rule_resources("train"),
    conda:
        "../../envs/seathru.yaml"
    shell:
        "seathru train --cameras {input:q}/cameras.json --out {params.out:q} "
        "--checkpoint-dir {params.checkpoints:q} --threads {threads} {params.flags} > {log:q} 2>&1"
