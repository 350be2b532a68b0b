//! PAFSIS global planning (paper §2.2): a mission `FROM:TO` on the topological map becomes the
//! shortest sequence of waypoints (places) and the edges between them. Edge cost is its length
//! in metres; the search is petgraph's A* with a zero heuristic (Dijkstra), which is
//! deterministic for a given map.

use super::map::TopoMap;
use petgraph::graph::{DiGraph, NodeIndex};
use std::fmt;
use std::str::FromStr;

/// Why no plan could be made.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PlanError {
    #[error("mission \"{0}\" is not FROM:TO (two place names separated by ':', e.g. R9:D2)")]
    BadMission(String),
    #[error("map {map}: unknown place \"{name}\" in the mission; known places: {known}")]
    UnknownPlace { map: String, name: String, known: String },
    #[error("map {map}: no path from {from} to {to}; add edges that connect them")]
    Unreachable { map: String, from: String, to: String },
}

/// A mission: go from one place to another.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Mission {
    pub from: String,
    pub to: String,
}

impl FromStr for Mission {
    type Err = PlanError;

    fn from_str(s: &str) -> Result<Self, PlanError> {
        match s.split_once(':') {
            Some((a, b)) if !a.trim().is_empty() && !b.trim().is_empty() && !b.contains(':') => {
                Ok(Self { from: a.trim().to_string(), to: b.trim().to_string() })
            }
            _ => Err(PlanError::BadMission(s.to_string())),
        }
    }
}

impl fmt::Display for Mission {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}:{}", self.from, self.to)
    }
}

/// The global path: waypoints and the map edges joining them.
#[derive(Clone, Debug, PartialEq)]
pub struct Plan {
    /// Place names from start to goal (the start included; one place when already there).
    pub waypoints: Vec<String>,
    /// Indices into [`TopoMap::edges`], one per hop.
    pub edges: Vec<usize>,
    /// Total cost, m.
    pub length_m: f64,
}

/// Plans the shortest path for `mission` on `map`.
pub fn plan(map: &TopoMap, mission: &Mission) -> Result<Plan, PlanError> {
    let lookup = |name: &str| {
        map.place_index(name).ok_or_else(|| PlanError::UnknownPlace {
            map: map.source.display().to_string(),
            name: name.to_string(),
            known: map.places.iter().map(|p| p.name.as_str()).collect::<Vec<_>>().join(", "),
        })
    };
    let from = lookup(&mission.from)?;
    let to = lookup(&mission.to)?;

    let mut graph: DiGraph<usize, usize> = DiGraph::with_capacity(map.places.len(), map.edges.len());
    let nodes: Vec<NodeIndex> = (0..map.places.len()).map(|i| graph.add_node(i)).collect();
    for (k, e) in map.edges.iter().enumerate() {
        // Both ends exist: TopoMap validated them.
        if let (Some(a), Some(b)) = (map.place_index(&e.from), map.place_index(&e.to)) {
            graph.add_edge(nodes[a], nodes[b], k);
        }
    }
    let found =
        petgraph::algo::astar(&graph, nodes[from], |n| n == nodes[to], |e| map.edges[*e.weight()].cost_m(), |_| 0.0);
    let Some((length_m, path)) = found else {
        return Err(PlanError::Unreachable {
            map: map.source.display().to_string(),
            from: mission.from.clone(),
            to: mission.to.clone(),
        });
    };
    let edges = path
        .windows(2)
        .filter_map(|w| {
            let (a, b) = (graph[w[0]], graph[w[1]]);
            // The cheapest edge between the pair (there is at most one per direction).
            graph.edges_connecting(nodes[a], nodes[b]).map(|e| *e.weight()).next()
        })
        .collect();
    Ok(Plan { waypoints: path.iter().map(|&n| map.places[graph[n]].name.clone()).collect(), edges, length_m })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A square A–B–C–D with a long diagonal A→C.
    const SQUARE: &str = r#"
        [[place]]
        name = "A"
        kind = "junction"
        [[place]]
        name = "B"
        kind = "corner"
        [[place]]
        name = "C"
        kind = "junction"
        [[place]]
        name = "X"
        kind = "room"
        [[edge]]
        from = "A"
        to = "B"
        heading_deg = 0
        actions = [{ do = "follow_corridor", length_m = 3.0 }]
        [[edge]]
        from = "B"
        to = "C"
        heading_deg = 90
        actions = [{ do = "follow_corridor", length_m = 4.0 }]
        [[edge]]
        from = "A"
        to = "C"
        heading_deg = 45
        actions = [{ do = "follow_corridor", length_m = 8.0 }]
    "#;

    #[test]
    fn mission_parsing() {
        assert_eq!("R9:D2".parse::<Mission>().unwrap(), Mission { from: "R9".into(), to: "D2".into() });
        for bad in ["R9", ":D2", "R9:", "a:b:c", ""] {
            assert!(matches!(bad.parse::<Mission>(), Err(PlanError::BadMission(_))), "{bad}");
        }
    }

    #[test]
    fn shortest_path_by_length() {
        let map = TopoMap::parse(SQUARE, "square.toml").unwrap();
        let p = plan(&map, &"A:C".parse().unwrap()).unwrap();
        assert_eq!(p.waypoints, ["A", "B", "C"]);
        assert_eq!(p.edges, [0, 1]);
        assert_eq!(p.length_m, 7.0);
        let longer = SQUARE.replace("length_m = 4.0", "length_m = 6.0");
        let map = TopoMap::parse(&longer, "square.toml").unwrap();
        let p = plan(&map, &"A:C".parse().unwrap()).unwrap();
        assert_eq!(p.waypoints, ["A", "C"]);
        assert_eq!(p.length_m, 8.0);
    }

    #[test]
    fn unreachable_and_unknown() {
        let map = TopoMap::parse(SQUARE, "square.toml").unwrap();
        let e = plan(&map, &"C:A".parse().unwrap()).unwrap_err();
        assert!(matches!(e, PlanError::Unreachable { .. }), "edges are directed: {e}");
        let e = plan(&map, &"A:X".parse().unwrap()).unwrap_err().to_string();
        assert!(e.contains("square.toml") && e.contains("no path from A to X"), "{e}");
        let e = plan(&map, &"A:Q".parse().unwrap()).unwrap_err().to_string();
        assert!(e.contains("unknown place \"Q\"") && e.contains("A, B, C, X"), "{e}");
    }

    #[test]
    fn already_there() {
        let map = TopoMap::parse(SQUARE, "square.toml").unwrap();
        let p = plan(&map, &"B:B".parse().unwrap()).unwrap();
        assert_eq!((p.waypoints.len(), p.edges.len(), p.length_m), (1, 0, 0.0));
    }
}
