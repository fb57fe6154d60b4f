"""Tower database: the cells plausible where the receiver is, grouped by site.

The envelope keeps timing far better than identity, so the cell search leans on this list:
it scores only these PCIs (known-PCI mode) and a site, not a sector, is the TDOA anchor.
A site's position and frame-timing offset may be unknown (null): then it still names cells
but cannot anchor a position fix.

Within a site, either every sector gives its EARFCN or none does (sectors of a site are paired
by carrier: a cell without one would silently drop out of the pair search), a PCI appears at
most once per carrier (two such sectors cannot be told apart), and the position is given
whole (latitude and longitude) or not at all.

```yaml
name: campus
sites:
  - name: A
    latitude_deg: 38.985851      # optional
    longitude_deg: -76.947617    # optional
    height_m: 30.0               # optional, antenna height above ground
    timing_offset_us: 3120.4     # optional, frame timing vs network time (estimate)
    cells:
      - {pci: 120, earfcn: 2000}
```
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from deepsync.configio import ConfigError, load_yaml, require_list, require_mapping
from deepsync.lte.cell import check_pci
from deepsync.lte.earfcn import downlink_frequency_hz


@dataclass(frozen=True)
class TowerCell:
    pci: int
    earfcn: int | None
    site: str

    @property
    def carrier_hz(self) -> float | None:
        return None if self.earfcn is None else downlink_frequency_hz(self.earfcn)


@dataclass(frozen=True)
class TowerSite:
    name: str
    latitude_deg: float | None
    longitude_deg: float | None
    height_m: float | None
    timing_offset_us: float | None
    cells: tuple[TowerCell, ...]


@dataclass(frozen=True)
class TowerDatabase:
    name: str
    sites: tuple[TowerSite, ...]

    @property
    def cells(self) -> tuple[TowerCell, ...]:
        return tuple(cell for site in self.sites for cell in site.cells)

    @property
    def pcis(self) -> list[int]:
        return sorted({cell.pci for cell in self.cells})

    def cells_with_pci(self, pci: int) -> list[TowerCell]:
        """Every database cell using ``pci`` (PCIs repeat across a network, on other sites)."""
        return [cell for cell in self.cells if cell.pci == pci]

    def cosited_pairs(self) -> list[tuple[int, int]]:
        """Pairs of PCIs on one site and one carrier (or carriers not given, which the parser
        allows only for a whole site): sectors whose sync codes arrive at the same time and
        add up before the square law."""
        pairs = set()
        for site in self.sites:
            for i, a in enumerate(site.cells):
                for b in site.cells[i + 1 :]:
                    if a.pci != b.pci and a.earfcn == b.earfcn:
                        pairs.add((min(a.pci, b.pci), max(a.pci, b.pci)))
        return sorted(pairs)


_SITE_KEYS = {"name", "latitude_deg", "longitude_deg", "height_m", "timing_offset_us", "cells"}


def _optional_number(site: dict, key: str, where: str, low: float, high: float) -> float | None:
    value = site.get(key)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not low <= value <= high:
        raise ConfigError(f"{where}.{key}: expected a number in [{low:g}, {high:g}], got {value!r}")
    return float(value)


def _check_site_cells(cells: list[TowerCell], at: str) -> None:
    """Sectors of a site are paired by carrier (``cosited_pairs``), so either all give their
    EARFCN or none does; and one PCI twice on one carrier of a site is one cell, listed twice
    or mistyped."""
    missing = [j for j, cell in enumerate(cells) if cell.earfcn is None]
    if 0 < len(missing) < len(cells):
        given = [j for j in range(len(cells)) if j not in missing]
        raise ConfigError(
            f"{at}.cells: earfcn given for {_cell_list(given)} but not for "
            f"{_cell_list(missing)}; give it for every sector of site {cells[0].site!r} or for "
            "none (sectors of a site are paired by carrier)"
        )
    first: dict[tuple[int, int | None], int] = {}
    for j, cell in enumerate(cells):
        key = (cell.pci, cell.earfcn)
        if key in first:
            carrier = "without an EARFCN" if cell.earfcn is None else f"on EARFCN {cell.earfcn}"
            raise ConfigError(
                f"{at}.cells[{j}].pci: PCI {cell.pci} {carrier} is already used by "
                f"{at}.cells[{first[key]}] (two sectors of one site with the same PCI on one "
                "carrier cannot be told apart)"
            )
        first[key] = j


def _cell_list(indices: list[int]) -> str:
    return ", ".join(f"cells[{j}]" for j in indices)


def parse_tower_database(data: object, where: str = "towers") -> TowerDatabase:
    """Tower database from a mapping (see the module docstring); errors name the field."""
    top = require_mapping(data, where)
    unknown = sorted(set(top) - {"name", "sites"})
    if unknown:
        raise ConfigError(f"{where}: unknown key {', '.join(unknown)} (known: name, sites)")
    sites = []
    names = set()
    for i, raw_site in enumerate(require_list(top.get("sites"), f"{where}.sites")):
        at = f"{where}.sites[{i}]"
        site = dict(require_mapping(raw_site, at))
        unknown = sorted(set(site) - _SITE_KEYS)
        if unknown:
            raise ConfigError(f"{at}: unknown key {', '.join(unknown)} (known: {', '.join(sorted(_SITE_KEYS))})")
        name = site.get("name")
        if not isinstance(name, str) or not name or name in names:
            raise ConfigError(f"{at}.name: a unique, non-empty site name is required, got {name!r}")
        names.add(name)
        cells = []
        for j, raw_cell in enumerate(require_list(site.get("cells"), f"{at}.cells")):
            cell_at = f"{at}.cells[{j}]"
            cell = require_mapping(raw_cell, cell_at)
            if set(cell) - {"pci", "earfcn"} or "pci" not in cell:
                raise ConfigError(f"{cell_at}: expected keys pci and optional earfcn, got {sorted(cell)}")
            try:
                pci = check_pci(cell["pci"])
                earfcn = cell.get("earfcn")
                if earfcn is not None:
                    downlink_frequency_hz(earfcn)  # validates it
                    earfcn = int(earfcn)
            except ValueError as error:
                raise ConfigError(f"{cell_at}: {error}") from None
            cells.append(TowerCell(pci, earfcn, name))
        if not cells:
            raise ConfigError(f"{at}.cells: a site needs at least one cell")
        _check_site_cells(cells, at)
        latitude = _optional_number(site, "latitude_deg", at, -90, 90)
        longitude = _optional_number(site, "longitude_deg", at, -180, 180)
        if (latitude is None) != (longitude is None):
            raise ConfigError(f"{at}: give both latitude_deg and longitude_deg, or neither "
                              "(half a position cannot anchor a fix)")
        sites.append(TowerSite(
            name=name,
            latitude_deg=latitude,
            longitude_deg=longitude,
            height_m=_optional_number(site, "height_m", at, 0, 1000),
            timing_offset_us=_optional_number(site, "timing_offset_us", at, 0, 10000),
            cells=tuple(cells),
        ))
    if not sites:
        raise ConfigError(f"{where}.sites: the database lists no sites")
    name = top.get("name", "")
    if not isinstance(name, str):
        raise ConfigError(f"{where}.name: expected a string, got {name!r}")
    return TowerDatabase(name, tuple(sites))


def load_tower_database(path: str | Path) -> TowerDatabase:
    return parse_tower_database(load_yaml(path), str(path))
