//! Where a Modbus TCP unit id goes: a bus and a unit address on it.
//!
//! With a `[[modbus_tcp.unit_map]]`, its ranges route as written, drives
//! configured or not (a range is an explicit choice, e.g. to reach a drive
//! being commissioned). Without one, every configured drive is reachable
//! under its own unit number; with several buses, a unit number configured
//! on two of them is ambiguous and reaches neither (the daemon says so when
//! it starts). Anything else is answered 0x0A, gateway path unavailable.

use crate::config::modbus_tcp::UnitMapEntry;

/// A unit's destination.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Route {
    /// Index of the bus in the plant's bus list.
    pub bus: usize,
    /// The unit address on that bus.
    pub unit: u8,
}

/// The routing table of one listener.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct UnitRoutes {
    /// Destination of each unit id 1..=255 (index 0 unused).
    routes: Vec<Option<Route>>,
    /// Buses a broadcast (unit 0) goes to: every bus the table reaches.
    broadcast: Vec<usize>,
}

/// What the table needs to know of one bus.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BusUnits {
    /// The bus's name, as the unit map names it.
    pub name: String,
    /// Its configured drives' units.
    pub units: Vec<u8>,
}

impl UnitRoutes {
    /// Builds the table from the unit map (names already validated against
    /// `buses`); also returns warnings for the operator.
    pub fn build(map: &[UnitMapEntry], buses: &[BusUnits]) -> (UnitRoutes, Vec<String>) {
        let mut routes = vec![None; 256];
        let mut warnings = Vec::new();
        if map.is_empty() {
            for (index, bus) in buses.iter().enumerate() {
                for &unit in &bus.units {
                    routes[usize::from(unit)] = Some(Route { bus: index, unit });
                }
            }
            for unit in 1..=255u8 {
                let on: Vec<&str> = buses
                    .iter()
                    .filter(|b| b.units.contains(&unit))
                    .map(|b| b.name.as_str())
                    .collect();
                if on.len() > 1 {
                    routes[usize::from(unit)] = None;
                    warnings.push(format!(
                        "Modbus TCP unit {unit} is configured on buses {}: it is unreachable until [[modbus_tcp.unit_map]] says where it goes",
                        on.join(" and ")
                    ));
                }
            }
        } else {
            for entry in map {
                let Some(bus) = buses.iter().position(|b| b.name == entry.bus()) else {
                    warnings.push(format!(
                        "the unit map names bus \"{}\", which is not configured",
                        entry.bus()
                    ));
                    continue;
                };
                let units = entry.units();
                for tcp_unit in units.first..=units.last {
                    if let Some(unit) = entry.bus_unit(tcp_unit) {
                        routes[usize::from(tcp_unit)] = Some(Route { bus, unit });
                    }
                }
            }
        }
        let mut broadcast: Vec<usize> = routes.iter().flatten().map(|r| r.bus).collect();
        broadcast.sort_unstable();
        broadcast.dedup();
        (UnitRoutes { routes, broadcast }, warnings)
    }

    /// Where `unit` goes; `None` for unit 0 and unmapped units.
    pub fn route(&self, unit: u8) -> Option<Route> {
        self.routes.get(usize::from(unit)).copied().flatten()
    }

    /// The buses a broadcast goes to.
    pub fn broadcast_buses(&self) -> &[usize] {
        &self.broadcast
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::modbus_tcp::UnitRange;
    use toml::Spanned;

    fn bus(name: &str, units: &[u8]) -> BusUnits {
        BusUnits {
            name: name.to_string(),
            units: units.to_vec(),
        }
    }

    fn entry(units: (u8, u8), bus: &str, bus_units: Option<(u8, u8)>) -> UnitMapEntry {
        UnitMapEntry {
            units: Spanned::new(
                0..0,
                UnitRange {
                    first: units.0,
                    last: units.1,
                },
            ),
            bus: Spanned::new(0..0, bus.to_string()),
            bus_units: bus_units.map(|(first, last)| Spanned::new(0..0, UnitRange { first, last })),
        }
    }

    #[test]
    fn one_bus_without_a_map_reaches_its_drives_one_to_one() {
        let (r, warnings) = UnitRoutes::build(&[], &[bus("line1", &[1, 2, 3, 4])]);
        assert!(warnings.is_empty());
        assert_eq!(r.route(3), Some(Route { bus: 0, unit: 3 }));
        assert_eq!(r.route(5), None);
        assert_eq!(r.route(0), None);
        assert_eq!(r.broadcast_buses(), [0]);
    }

    #[test]
    fn the_map_sends_ranges_to_buses_with_an_offset() {
        let map = [
            entry((1, 32), "A", None),
            entry((101, 132), "B", Some((1, 32))),
        ];
        let (r, warnings) = UnitRoutes::build(&map, &[bus("A", &[1]), bus("B", &[1])]);
        assert!(warnings.is_empty());
        assert_eq!(r.route(1), Some(Route { bus: 0, unit: 1 }));
        assert_eq!(r.route(32), Some(Route { bus: 0, unit: 32 }));
        assert_eq!(r.route(101), Some(Route { bus: 1, unit: 1 }));
        assert_eq!(r.route(132), Some(Route { bus: 1, unit: 32 }));
        assert_eq!(r.route(33), None);
        assert_eq!(r.route(100), None);
        assert_eq!(r.route(133), None);
        assert_eq!(r.broadcast_buses(), [0, 1]);
    }

    #[test]
    fn without_a_map_a_unit_on_two_buses_is_unreachable_and_reported() {
        let (r, warnings) = UnitRoutes::build(&[], &[bus("A", &[1, 2]), bus("B", &[2, 3])]);
        assert_eq!(r.route(1), Some(Route { bus: 0, unit: 1 }));
        assert_eq!(r.route(3), Some(Route { bus: 1, unit: 3 }));
        assert_eq!(r.route(2), None);
        assert_eq!(warnings.len(), 1);
        assert!(warnings[0].contains("unit 2 is configured on buses A and B"));
    }

    #[test]
    fn broadcasts_reach_only_mapped_buses() {
        let map = [entry((1, 8), "B", None)];
        let (r, _) = UnitRoutes::build(&map, &[bus("A", &[1]), bus("B", &[1])]);
        assert_eq!(r.broadcast_buses(), [1]);
    }
}
