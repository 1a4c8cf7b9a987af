rule report:
    """One table and plots across every dataset of the sheet (and its sweep variants); failed
    datasets with their error; the frontier of quality against time per dataset."""
    input:
        summaries=lambda wildcards: [f"{dataset_dir(ds, 'evaluate')}/summary.json"
                                     for ds in evaluated_datasets()],
        sheet=config["datasets"],
    output:
        table=report(f"{REPORT_DIR}/summary.csv", caption="../report/summary.rst",
                     category="Summary"),
        html=f"{REPORT_DIR}/summary.html",
        psnr_time=report(f"{REPORT_DIR}/psnr_vs_time.png", caption="../report/psnr_vs_time.rst",
                         category="Plots"),
        speed_error=report(f"{REPORT_DIR}/speed_vs_error.png",
                           caption="../report/speed_vs_error.rst", category="Plots"),
        water=report(f"{REPORT_DIR}/water_parameters.png",
                     caption="../report/water_parameters.rst", category="Plots"),
        strips=report(directory(f"{REPORT_DIR}/strips"), patterns=["{name}.png"],
                      caption="../report/strips.rst", category="Image strips"),
        frontier=report(directory(f"{REPORT_DIR}/frontier"), patterns=["{name}.png"],
                        caption="../report/frontier.rst", category="Speed against error"),
        frontier_table=report(f"{REPORT_DIR}/frontier.csv",
                              caption="../report/frontier_table.rst",
                              category="Speed against error"),
    params:
        results=lambda wildcards: RESULTS,
        logs=lambda wildcards: LOGS,
        out=lambda wildcards, output: Path(output.table).parent,
        flags=cli_flags(config.get("report") or {}),
        variants=sweep_flags(config.get("sweep")),
    log:
        f"{LOGS}/report.log",
    conda:
        "../../envs/seathru.yaml"
    shell:
        "seathru report --results {params.results:q} --datasets {input.sheet:q} "
        "--logs {params.logs:q} --out {params.out:q} {params.variants} {params.flags} "
        "> {log:q} 2>&1"
