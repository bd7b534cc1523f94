# Sourced by the device scripts, from the repository root on the GPU machine: the package's kernels/ and configs/
# links (`pip install -e .` is not possible there) and Warp from the kit in /tmp/site.
ln -sfn ../kernels warpsense/kernels; ln -sfn ../configs warpsense/configs
export PYTHONPATH=/tmp/site:$PWD
# A bytecode cache that a new process can read: the lent machine's torch has none (a new process compiles ~1,760 of
# torch's modules from source, ~5 s of its first epoch), which a pip install has. Without it each process
# of a study's pool or of torchrun pays that again; with it the first process writes the cache for the next ones.
unset PYTHONDONTWRITEBYTECODE
export PYTHONPYCACHEPREFIX=/tmp/pycache
