"""Back end: incremental estimation (iSAM2), sequential Givens estimator, data snooping."""
