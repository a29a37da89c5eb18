"""mshoot_studies: applications of mshoot_core: the case, the study, sweeps, ``mshoot``."""
