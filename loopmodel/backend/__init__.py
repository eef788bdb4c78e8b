"""Back end: incremental estimation (iSAM2) and the sequential Givens estimator with data snooping."""
