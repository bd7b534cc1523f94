"""One module per `warpsense` command: each exposes a plain function that the CLI (`warpsense.cli`) calls after
parsing its arguments. Commands may import any layer below them (train, data, camera, ops); nothing below imports
a command."""
