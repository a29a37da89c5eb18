"""BOPTEST test case in core: the test case folder, the plant (real FMU), the starts count."""
import math

from mshoot_core.boptest.plant import BoptestPlant, recorded_outputs
from mshoot_core.boptest.testcase import PRICE_SCENARIOS, TestCase
from mshoot_studies.boptest_report import count_starts
import numpy as np
import pandas as pd
import pytest


def test_test_case_files(boptest_case: TestCase) -> None:
    case = boptest_case
    assert case.area_m2 == 192.0
    assert case.days == {'peak_heat_day': 23, 'typical_heat_day': 115}
    assert sorted(case.power_outputs) == ['reaPFan_y', 'reaPHeaPum_y', 'reaPPumEmi_y']
    assert case.zone_temperature_outputs == {'1': ['reaTZon_y']}
    assert case.co2_outputs == {'1': ['reaCO2RooAir_y']}
    assert case.zones == ['1'] and list(case.energy_outputs) == ['ElectricPower']
    assert case.fmu_path == case.directory / 'wrapped.fmu'
    assert case.price_column('dynamic', 'GasPower') == 'PriceGasPower'
    assert case.emission_column('ElectricPower') == 'EmissionsElectricPower'


def test_test_periods(boptest_case: TestCase) -> None:
    day = 86400.0
    assert boptest_case.test_period('peak_heat_day') == (9 * day, 16 * day, 30 * day)
    assert boptest_case.test_period('typical_heat_day', 1, 2) == (107 * day, 108 * day, 110 * day)
    with pytest.raises(ValueError, match='unknown test period'):
        boptest_case.test_period('peak_cool_day')
    with pytest.raises(ValueError, match='length_days'):
        boptest_case.test_period('peak_heat_day', length_days=0)


def test_lookup_forward_fills(boptest_case: TestCase) -> None:
    case = boptest_case
    raw = pd.read_csv(case.directory / 'Resources' / 'prices.csv')
    column = PRICE_SCENARIOS['highly_dynamic']
    # a row where the price changes: at that row's time the new value, just before the old one
    k = int(np.flatnonzero(np.diff(raw[column].to_numpy()))[10]) + 1
    t_row = float(raw['time'][k])
    got = case.lookup(column, [t_row - 1.0, t_row, t_row + 899.0])
    assert got.tolist() == [raw[column][k - 1], raw[column][k], raw[column][k]]
    frame = case.lookup_frame(['LowerSetp[1]', 'TDryBul'], [0.0, 450.0])
    assert frame.index.tolist() == [0.0, 450.0]
    assert frame['TDryBul'].tolist() == [274.15, 274.15]
    with pytest.raises(ValueError, match='unknown test case data column'):
        case.lookup('LowerSetp', [0.0])
    with pytest.raises(ValueError, match='outside the data'):
        case.lookup('TDryBul', [-1.0])
    with pytest.raises(ValueError, match='unknown price scenario'):
        case.price_column('cheap')


def test_missing_folder_is_clear(tmp_path) -> None:
    with pytest.raises(FileNotFoundError, match='BOPTEST test case folder not found'):
        TestCase.load(tmp_path / 'nowhere')


def test_plant_overwrites_and_records(boptest_case: TestCase) -> None:
    """The real FMU: a setpoint overwrite stops the heat pump, releasing it hands control back."""
    warmup_start, start, _ = boptest_case.test_period('peak_heat_day', 0.25, 1)
    with BoptestPlant(boptest_case) as plant:
        assert plant.interface == 'CoSimulation'
        with pytest.raises(RuntimeError, match='call start'):
            plant.advance(start)
        plant.start(warmup_start)
        with pytest.raises(RuntimeError, match='one instance per process'):
            BoptestPlant(boptest_case).start(warmup_start)
        plant.advance(start)
        assert plant.time_s == start
        assert plant.outputs['reaHeaPumY_y'] > 0.1  # a cold January night: heating
        with pytest.raises(ValueError, match='unknown overwrite input'):
            plant.advance(start + 3600, {'oveTSet_activate': 1.0})
        with pytest.raises(ValueError, match='outside its range'):
            plant.advance(start + 3600, {'oveTSet_u': 20.0})
        with pytest.raises(ValueError, match='outside its range'):
            plant.advance(start + 3600, {'oveHeaPumY_u': math.nan})
        with pytest.raises(ValueError, match='cannot advance'):
            plant.advance(start - 60)
        assert plant.time_s == start  # nothing applied by the refused calls
        plant.advance(start + 3600, {'oveTSet_u': 278.15, 'oveHeaPumY_u': None}, sample_s=55)
        off = plant.records(start, start + 3600)
        plant.advance(start + 7200)
        released = plant.records(start + 3600, start + 7200)
    assert not plant.running
    # 55 s samples; the last step shortened to end on the hour
    steps = np.diff(off['time'].to_numpy())
    assert steps.max() == 55.0 and steps[-1] == 3600.0 - 65 * 55.0 and len(off) == 67
    assert np.isnan(off['oveTSet_u'].iloc[0]) and (off['oveTSet_u'].iloc[1:] == 278.15).all()
    assert off['oveHeaPumY_u'].isna().all()
    assert (off['reaTSet_y'].iloc[1:] == 278.15).all()
    assert off['reaPHeaPum_y'].iloc[-1] == 0.0 and off['reaTZon_y'].diff().iloc[-1] < 0
    assert released['oveTSet_u'].iloc[1:].isna().all()
    assert released['reaTSet_y'].iloc[-1] == pytest.approx(released['reaTSetHea_y'].iloc[-1]
                                                           + 0.2)
    assert released['reaHeaPumY_y'].iloc[-1] > 0.1
    assert np.diff(released['time'].to_numpy()).max() == 60.0
    # the instance is free again
    with BoptestPlant(boptest_case) as again:
        again.start(warmup_start)


def test_record_names_checked(boptest_case: TestCase) -> None:
    with pytest.raises(ValueError, match='not outputs'):
        BoptestPlant(boptest_case, record=['reaTZon_y', 'TZone'])
    # by default every output, as BOPTEST stores them; a run records kpis.json's and a card's
    plant = BoptestPlant(boptest_case)
    assert plant.recorded == tuple(plant.outputs_available) and len(plant.recorded) > 40
    assert recorded_outputs(boptest_case, ['reaTSet_y', 'reaTZon_y']) == [
        'reaTZon_y', 'reaPFan_y', 'reaPHeaPum_y', 'reaPPumEmi_y', 'reaCO2RooAir_y',
        'reaTSet_y']


def test_starts_by_hand() -> None:
    day = 86400.0
    y = [0.0, 0.5, 0.5, 0.0, 0.005, 1.0, 0.0, 0.2, 0.2]
    table = pd.DataFrame({'time': np.arange(len(y)) * day / 4, 'reaHeaPumY_y': y})
    # rising edges at samples 1, 5, 7 (0.005 is below the threshold 0.01)
    assert count_starts(table, 'reaHeaPumY_y') == (3, 3 / 2.0)
    # window (t0, t1]: the edge at sample 1 is excluded when the window starts there
    assert count_starts(table, 'reaHeaPumY_y', start_s=day / 4, end_s=2 * day) == (2, 2 / 1.75)
    assert count_starts(table, 'reaHeaPumY_y', threshold=0.3)[0] == 2  # edges at 1 and 5 only
    with pytest.raises(ValueError, match='lacks the column'):
        count_starts(table.drop(columns='reaHeaPumY_y'), 'reaHeaPumY_y')
