"""Quality decisions from an RTD: lot boundaries and diversion windows (``lots``), funnel plots
and OOS fractions (``funnel``), the analysis of a measured tracer profile through to them
(``analysis``) and the seed's chapter 6 reproduction (``reproduce``).

Builds on ``twin_core.rtd`` (convolution, profiles, truncation, the RTD tables); nothing in
``twin_core.rtd`` imports this package.
"""
