"""The `touchdown` command's workflows: bags read, core called, bags, tables and figures written.

- `commands`: each subcommand as a function with typed arguments (what the CLI calls).
- `offline`: one recorded drop estimated (bag in, estimate, summary and output bag out).
- `training_data`, `optimise`, `calibrate` (stage 1), `train` (stage 2 and the coefficient file).
- `evaluate`: the constant model against PKBKR, leave-one-experiment-out.
- `diagnose`, `candidates`: the workbench (where the model fails, which effect it lacks).
- `report/`: figures, tables and the Markdown / JSON / CSV files of every command.
- `outputs`, `progress`: where a command writes (nothing partial), and its progress lines.
"""
