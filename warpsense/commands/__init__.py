"""One module per `warpsense` command (`warpsense.cli.COMMANDS`). Each declares its own arguments
(``register(commands, name)``, which adds its parser to the top-level subparsers) and runs them (``run(args)``,
which checks the options that depend on each other and calls the command's function, importable with plain
arguments: `train.run_train`, `eval.run_eval`, ...; it returns the exit code).

Every `warpsense` call builds every command's parser, so a command module imports at its top only what its
arguments need (argparse, `warpsense.choices`, `warpsense.config`, `warpsense.files`); its work imports the rest
(torch, Warp, the model) inside the function that runs it. That keeps `warpsense --help` quick, and lets
`warpsense.cli.main` set the OpenMP defaults before torch loads. Options several commands share are in `options`.

Commands may import any layer below them (train, data, camera, ops); nothing below imports a command."""
