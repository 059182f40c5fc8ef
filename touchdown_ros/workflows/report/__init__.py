"""Figures, tables and the Markdown / JSON / CSV files the commands write, built from what core returns
(matplotlib without a display).

- `plotting`: what every figure shares (backend, time axis, saving).
- `estimate`: `touchdown estimate` (figures of one bag, summary.json / summary.md).
- `evaluation`: `touchdown evaluate` (the paper's figures 2-8, parameter maps, evaluation.*).
- `diagnosis`, `diagnosis_figures`: `touchdown diagnose` (diagnosis.*, errors.csv, ranking.csv, figures).
"""
