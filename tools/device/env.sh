# Sourced by the device scripts, from the repository root on the GPU machine: the package's kernels/ and configs/
# links (`pip install -e .` is not possible there) and Warp from the kit in /tmp/site.
ln -sfn ../kernels warpsense/kernels; ln -sfn ../configs warpsense/configs
export PYTHONPATH=/tmp/site:$PWD
