"""Zone models behind one interface: generic Python, FMI (fmpy) and scikit-learn."""
from mshoot_core.models.base import IntervalJacobians, Model
from mshoot_core.models.r1c1 import R1C1Model, R1C1Parameters

__all__ = ['IntervalJacobians', 'Model', 'R1C1Model', 'R1C1Parameters']
