"""Sensor calibration: the project's Poisson-Gaussian noise (noise.shot, noise.read, in units of the white level)
estimated from real raw captures, per CFA channel with 95% intervals (`warpsense calibrate`,
docs/guide/calibrate.md).

- `captures`: a capture read into CFA site planes with its ADC's bounds (`warpsense.data.raw` reads the files);
- `local`, `levels`, `model`, `fit`, `single`: one capture's estimate from its smooth regions (Foi et al. 2008);
- `series`: the photon-transfer estimate from flat-field pairs and dark frames (EMVA 1288);
- `report`: electrons, the preset and the plot; `batch`: the command's work over a batch of captures.
"""
