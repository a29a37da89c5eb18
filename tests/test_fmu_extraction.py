"""
FMUs are extracted once into the cache, keyed by their hash.

Bad ones leave nothing behind; FMI 3.0 FMUs get a plain answer.
"""
import os
import pathlib
import tempfile
import threading
import zipfile

from mshoot_core import fmu_cache
from mshoot_core.models.fmi import FmiModel, r1c1_fmi_model
import pytest

FMI3_DESCRIPTION = """<?xml version="1.0" encoding="UTF-8"?>
<fmiModelDescription fmiVersion="3.0" modelName="Zone3" instantiationToken="{8c4e810f-3df3}">
  <CoSimulation modelIdentifier="Zone3"/>
  <ModelVariables>
    <Float64 name="time" valueReference="0" causality="independent" variability="continuous"/>
    <Float64 name="T" valueReference="1" causality="output" variability="continuous"/>
  </ModelVariables>
  <ModelStructure><Output valueReference="1"/></ModelStructure>
</fmiModelDescription>
"""


@pytest.fixture
def isolated(tmp_path, monkeypatch):
    """Temporary folders and FMU extractions under tmp_path (the drivers stay where they are)."""
    temp = tmp_path / 'tmp'
    temp.mkdir()
    monkeypatch.setattr(tempfile, 'tempdir', str(temp))
    monkeypatch.setenv('TMPDIR', str(temp))
    extracted = tmp_path / 'cache' / fmu_cache.EXTRACTED
    monkeypatch.setattr(fmu_cache, 'extracted_dir',
                        lambda path: extracted / fmu_cache.file_sha256(path)[:32])
    return temp, extracted


def _everything(folder: pathlib.Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob('*')) if folder.exists() \
        else []


def _zip(path: pathlib.Path, members: dict[str, str | bytes]) -> pathlib.Path:
    with zipfile.ZipFile(path, 'w') as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    return path


def test_bad_fmus_leave_no_temporary_folder(isolated, tmp_path):
    temp, extracted = isolated
    r1c1 = fmu_cache.find_fmu('r1c1')
    with zipfile.ZipFile(r1c1) as archive:
        description = archive.read('modelDescription.xml')
    cases = {
        'not_a_zip.fmu': (b'this is not a zip archive', r'not an FMU: not a ZIP archive'),
        'no_description.fmu': ({'binaries/readme.txt': 'nothing'},
                               r'not a readable FMU: its modelDescription.xml could not be read'),
        'traversal.fmu': ({'modelDescription.xml': description, '../evil.txt': 'x'},
                          r"illegal path '../evil.txt'"),
        'no_binary.fmu': ({'modelDescription.xml': description},
                          r'no_binary.fmu: no binary for this platform: expected .*R1C1.so'),
    }
    for name, (content, message) in cases.items():
        path = tmp_path / name
        if isinstance(content, bytes):
            path.write_bytes(content)
        else:
            _zip(path, content)
        with pytest.raises(ValueError, match=message):
            r1c1_fmi_model(fmi_type='ModelExchange', fmu_path=path)
    assert _everything(temp) == []  # no temporary folder anywhere
    assert not (tmp_path / 'evil.txt').exists()
    # only the archive that extracted and read well stays, complete, in the cache
    kept = [p.name for p in extracted.iterdir()]
    assert kept == [fmu_cache.file_sha256(tmp_path / 'no_binary.fmu')[:32]]
    assert not any(p.name.startswith(fmu_cache.STAGING_PREFIX) for p in extracted.iterdir())


def test_fmi3_fmus_are_refused_plainly(isolated, tmp_path):
    temp, extracted = isolated
    path = _zip(tmp_path / 'zone3.fmu', {'modelDescription.xml': FMI3_DESCRIPTION})
    with pytest.raises(ValueError, match=r'zone3.fmu: FMI 3.0 FMUs are not supported yet '
                                         r"\(fmiVersion '3.0'\); export the model as an FMI "
                                         r'2.0 FMU'):
        FmiModel(path, inputs=[], states=[], outputs=['T'])
    assert _everything(temp) == [] and _everything(extracted) == []


def test_an_fmu_is_extracted_once_for_every_model_and_process(isolated, tmp_path):
    """Same bytes, same folder (also under another name); concurrent extractions agree."""
    _, extracted = isolated
    r1c1 = fmu_cache.find_fmu('r1c1')
    copy = tmp_path / 'renamed.fmu'
    copy.write_bytes(r1c1.read_bytes())
    folders = []
    errors = []

    def extract(path):
        try:
            folders.append(fmu_cache.extract_fmu(path))
        except Exception as error:  # noqa: BLE001 - collected for the assertion
            errors.append(error)

    threads = [threading.Thread(target=extract, args=(p,)) for p in (r1c1, copy) * 3]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert errors == [] and len(set(folders)) == 1
    with r1c1_fmi_model(fmi_type='CoSimulation', fmu_path=copy) as model:
        assert model._unzip_dir == folders[0]
    assert [p.name for p in extracted.iterdir()] == [folders[0].name]
    assert (folders[0] / 'modelDescription.xml').is_file()
    assert os.listdir(folders[0] / 'binaries')


def _fields(value: object, path: tuple = ()) -> object:
    """Return fmpy's description as nested tuples of its fields (its classes compare by id)."""
    import attrs
    if attrs.has(type(value)):
        if id(value) in path:  # (a reference back up the tree)
            return '<cycle>'
        return (type(value).__name__, tuple((f.name, _fields(getattr(value, f.name),
                                                             (*path, id(value))))
                                            for f in attrs.fields(type(value))))
    if isinstance(value, (list, tuple)):
        return tuple(_fields(item, path) for item in value)
    if isinstance(value, dict):
        return tuple(sorted((key, _fields(item, path)) for key, item in value.items()))
    return repr(value)


def test_a_cached_fmu_is_validated_once(isolated, monkeypatch):
    """
    The first model of an FMU file validates its modelDescription; later ones load what it read.

    The description read is kept beside the marker (a pickle) and loaded by later models, the
    same description as the XML's; without it, or damaged, the XML is read again (not
    validated); without the marker (a cache of an older mshoot), validated again. Each model
    stands for another process (the description read once in a process is kept: the next
    test).
    """
    from mshoot_core.models import fmi
    monkeypatch.setattr(fmi, '_DESCRIPTIONS', {})
    validations = []
    read = fmi.fmpy.read_model_description

    def recorded(*args, **kwargs):
        validations.append(kwargs.get('validate', True))
        return read(*args, **kwargs)
    monkeypatch.setattr(fmi.fmpy, 'read_model_description', recorded)
    for _ in range(2):
        fmi._DESCRIPTIONS.clear()  # (another process)
        with r1c1_fmi_model(fmi_type='ModelExchange') as model:
            folder = model._unzip_dir
            assert (folder / fmi.VALIDATED_MARKER).is_file()
            loaded = model.model_description
    assert validations == [True]  # the second model loaded the description kept
    assert _fields(loaded) == _fields(read(str(folder), validate=False))
    assert loaded.outputs and all(  # the structure kept: outputs refer to model variables
        any(o.variable is v for v in loaded.modelVariables) for o in loaded.outputs)
    kept = [p for p in folder.iterdir() if p.name.startswith('.mshoot-description')]
    assert len(kept) == 1  # (no temporary file left)
    kept[0].write_bytes(b'not a pickle')
    fmi._DESCRIPTIONS.clear()
    with r1c1_fmi_model(fmi_type='ModelExchange') as model:
        assert _fields(model.model_description) == _fields(loaded)
    assert validations == [True, False]  # read again (rewritten), not validated
    fmi._DESCRIPTIONS.clear()
    with r1c1_fmi_model(fmi_type='ModelExchange'):
        pass
    assert validations == [True, False]
    (folder / fmi.VALIDATED_MARKER).unlink()  # (a cache of an older mshoot)
    fmi._DESCRIPTIONS.clear()
    with r1c1_fmi_model(fmi_type='CoSimulation') as model:
        assert (folder / fmi.VALIDATED_MARKER).is_file()
    assert validations == [True, False, True]


def test_a_description_is_read_once_per_process(isolated, tmp_path, monkeypatch):
    """
    A process reads an FMU's modelDescription once: every later reader gets the same object.

    Read again when it changes: another FMU file (another folder of the cache), the extracted
    description touched or rewritten (its mtime, its size); and validated when a validating
    reader comes after one that did not validate.
    """
    from mshoot_core.models import fmi
    monkeypatch.setattr(fmi, '_DESCRIPTIONS', {})
    reads = []
    read = fmi._read_cached_description

    def counted(folder, label, validate):
        reads.append((folder.name, validate))
        return read(folder, label, validate)
    monkeypatch.setattr(fmi, '_read_cached_description', counted)
    copy = tmp_path / 'zone.fmu'
    copy.write_bytes(fmu_cache.find_fmu('r1c1').read_bytes())
    folder = fmu_cache.extract_fmu(copy)
    first = fmi.read_cached_description(folder, copy.name, validate=False)
    assert fmi.read_cached_description(folder, copy.name, validate=False) is first
    assert len(reads) == 1
    # a validating reader: read (validated) once, then shared by every reader, models too
    validated = fmi.read_cached_description(folder, copy.name)
    assert validated is not first and reads[-1] == (folder.name, True)
    with r1c1_fmi_model(fmi_type='ModelExchange', fmu_path=copy) as model:
        assert model.model_description is validated
    assert fmi.read_cached_description(folder, copy.name, validate=False) is validated
    assert len(reads) == 2
    # the extracted description touched: read again (the same content)
    xml = folder / 'modelDescription.xml'
    later = xml.stat().st_mtime_ns + 10**9
    os.utime(xml, ns=(later, later))
    touched = fmi.read_cached_description(folder, copy.name)
    assert touched is not validated and _fields(touched) == _fields(validated)
    assert fmi.read_cached_description(folder, copy.name) is touched and len(reads) == 3
    # the FMU file rewritten (another description): another folder, read
    with zipfile.ZipFile(fmu_cache.find_fmu('r1c1')) as archive:
        members = {name: archive.read(name) for name in archive.namelist()}
    members['modelDescription.xml'] = members['modelDescription.xml'].replace(
        b'description="R1C1 zone model', b'description="A rewritten R1C1 zone model')
    _zip(copy, members)
    rewritten = fmi.read_cached_description(fmu_cache.extract_fmu(copy), copy.name)
    assert rewritten.description.startswith('A rewritten R1C1') and len(reads) == 4
