"""
BOPTEST test cases run as mshoot plants (core, no ROS).

- :mod:`.testcase`: the test case folder (FMU, periods, KPI map, data, the libgfortran shim);
- :mod:`.forecasts`: a control model's forecast from the folder's data (interval means of the
  series its card names, the tightest band per zone, the price), with BOPTEST's errors;
- :mod:`.plant`: the FMU as one persistent plant instance with BOPTEST overwrites and records;
- :mod:`.kpi_calculator`: BOPTEST's KPIs from a record table (its calculator's definitions);
- :mod:`.period_scenario`: a test period as a scenario of the emulator and forecaster;
- :mod:`.card_plant`: a card of kind ``boptest`` as the emulator's plant;
- :mod:`.rule`: the rule-based pre-heating controller;
- :mod:`.supervision`: the supervisory :class:`~mshoot_core.controller.Controller` on a plant;
- :mod:`.weather`: the weather of a folder without ``weather.csv``, derived from its FMU.
"""
