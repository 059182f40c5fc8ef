"""The `touchdown` command's workflows: bags read, core called, bags, tables and figures written.

- `offline`: one recorded drop estimated (bag in, estimate bag and summary out), simulated drops written.
- `training_data`, `optimise`, `calibrate` (stage 1), `train` (stage 2 and the coefficient file).
- `evaluate`: the constant model against PKBKR, leave-one-experiment-out.
- `diagnose`, `candidates`: the workbench (where the model fails, which effect it lacks).
- `report`: figures, tables and the Markdown / JSON / CSV files of every command.
- `outputs`, `progress`: where a command writes, and its progress lines.
"""
