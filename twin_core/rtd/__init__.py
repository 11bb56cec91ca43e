"""Residence time distributions: models, fitting, denoising, truncation, the seed's chapter 6.

Modules are imported by name (``twin_core.rtd.models``, ``.fitting``, ``.denoise``, ...). Two of
them hold the project's one implementation of a concept that other packages use too:

- ``outliers``: :func:`~twin_core.rtd.outliers.hampel`, the Hampel identifier (``variant="seed"``
  for RTD profiles, ``"pearson"`` for the close-loop's NIR records);
- ``noise``: :func:`~twin_core.rtd.noise.pink_noise`, the 1/f noise generator (RTD profiles and
  the plant's NIR probe).
"""
