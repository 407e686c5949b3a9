//! A master control's road map: named nodes with positions and the edges between
//! them, from a JSON file. A goal position becomes the nearest node, and an order
//! follows the shortest path to it.
//!
//! ```json
//! {"mapId": "hall", "nodes": [{"id": "n1", "x": 0, "y": 0}, {"id": "n2", "x": 5, "y": 0}],
//!  "edges": [["n1", "n2"]], "oneWay": [["n2", "n3"]]}
//! ```
//! `edges` go both ways, `oneWay` only from the first node to the second.

use serde::Deserialize;
use std::collections::{BinaryHeap, HashMap};

/// A node.
#[derive(Clone, Debug, Deserialize, PartialEq)]
pub struct GraphNode {
    /// Its id, as orders name it.
    pub id: String,
    /// x, m.
    pub x: f64,
    /// y, m.
    pub y: f64,
}

#[derive(Deserialize)]
#[serde(rename_all = "camelCase", deny_unknown_fields)]
struct GraphFile {
    #[serde(default = "local")]
    map_id: String,
    nodes: Vec<GraphNode>,
    #[serde(default)]
    edges: Vec<(String, String)>,
    #[serde(default)]
    one_way: Vec<(String, String)>,
}

fn local() -> String {
    "local".into()
}

/// The road map.
#[derive(Clone, Debug)]
pub struct Graph {
    /// The map the positions are on.
    pub map_id: String,
    nodes: Vec<GraphNode>,
    index: HashMap<String, usize>,
    next: Vec<Vec<usize>>,
}

impl Graph {
    /// Reads a graph from JSON text (see the module's example).
    pub fn parse(text: &str) -> Result<Self, String> {
        let f: GraphFile = serde_json::from_str(text).map_err(|e| e.to_string())?;
        if f.nodes.is_empty() {
            return Err("no nodes".into());
        }
        let mut index = HashMap::new();
        for (i, n) in f.nodes.iter().enumerate() {
            if n.id.is_empty() || !(n.x.is_finite() && n.y.is_finite()) {
                return Err(format!(
                    "node {i}: empty id or a position that is not a number"
                ));
            }
            if index.insert(n.id.clone(), i).is_some() {
                return Err(format!("node {:?} is named twice", n.id));
            }
        }
        let mut next = vec![Vec::new(); f.nodes.len()];
        let mut add = |a: &str, b: &str, both: bool| -> Result<(), String> {
            let (Some(&i), Some(&j)) = (index.get(a), index.get(b)) else {
                return Err(format!("edge {a:?}-{b:?} names a node not in the graph"));
            };
            next[i].push(j);
            if both {
                next[j].push(i);
            }
            Ok(())
        };
        for (a, b) in &f.edges {
            add(a, b, true)?;
        }
        for (a, b) in &f.one_way {
            add(a, b, false)?;
        }
        Ok(Graph {
            map_id: f.map_id,
            nodes: f.nodes,
            index,
            next,
        })
    }

    /// The node named `id`.
    pub fn node(&self, id: &str) -> Option<&GraphNode> {
        self.index.get(id).map(|&i| &self.nodes[i])
    }

    /// The node nearest to (x, y).
    pub fn nearest(&self, x: f64, y: f64) -> &GraphNode {
        self.nodes
            .iter()
            .min_by(|a, b| {
                let da = (a.x - x).hypot(a.y - y);
                let db = (b.x - x).hypot(b.y - y);
                da.total_cmp(&db)
            })
            .expect("a graph has nodes")
    }

    /// The shortest path from node `from` to node `to` (both included), by length.
    pub fn path(&self, from: &str, to: &str) -> Option<Vec<&GraphNode>> {
        let (&s, &t) = (self.index.get(from)?, self.index.get(to)?);
        let mut dist = vec![f64::INFINITY; self.nodes.len()];
        let mut prev = vec![usize::MAX; self.nodes.len()];
        let mut heap = BinaryHeap::new();
        dist[s] = 0.0;
        heap.push(Visit(0.0, s));
        while let Some(Visit(d, i)) = heap.pop() {
            if i == t {
                break;
            }
            if d > dist[i] {
                continue;
            }
            for &j in &self.next[i] {
                let (a, b) = (&self.nodes[i], &self.nodes[j]);
                let nd = d + (a.x - b.x).hypot(a.y - b.y);
                if nd < dist[j] {
                    dist[j] = nd;
                    prev[j] = i;
                    heap.push(Visit(nd, j));
                }
            }
        }
        if !dist[t].is_finite() {
            return None;
        }
        let mut out = vec![&self.nodes[t]];
        let mut i = t;
        while i != s {
            i = prev[i];
            out.push(&self.nodes[i]);
        }
        out.reverse();
        Some(out)
    }
}

/// A node to visit, nearest first.
struct Visit(f64, usize);

impl PartialEq for Visit {
    fn eq(&self, o: &Self) -> bool {
        self.0.total_cmp(&o.0).is_eq()
    }
}
impl Eq for Visit {}
impl PartialOrd for Visit {
    fn partial_cmp(&self, o: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(o))
    }
}
impl Ord for Visit {
    fn cmp(&self, o: &Self) -> std::cmp::Ordering {
        o.0.total_cmp(&self.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const SQUARE: &str = r#"{"mapId": "hall",
        "nodes": [{"id": "a", "x": 0, "y": 0}, {"id": "b", "x": 10, "y": 0},
                  {"id": "c", "x": 10, "y": 10}, {"id": "d", "x": 0, "y": 10},
                  {"id": "e", "x": 1, "y": 1}],
        "edges": [["a", "b"], ["b", "c"], ["c", "d"], ["d", "a"]],
        "oneWay": [["e", "a"]]}"#;

    fn ids(p: Option<Vec<&GraphNode>>) -> Option<Vec<String>> {
        p.map(|p| p.into_iter().map(|n| n.id.clone()).collect())
    }

    #[test]
    fn shortest_paths_nearest_nodes_and_one_way_edges() {
        let g = Graph::parse(SQUARE).unwrap();
        assert_eq!(g.map_id, "hall");
        assert_eq!(ids(g.path("a", "c")).unwrap().len(), 3);
        assert_eq!(ids(g.path("a", "b")), Some(vec!["a".into(), "b".into()]));
        assert_eq!(ids(g.path("b", "b")), Some(vec!["b".into()]));
        assert_eq!(
            ids(g.path("e", "d")),
            Some(vec!["e".into(), "a".into(), "d".into()])
        );
        assert_eq!(ids(g.path("a", "e")), None, "one way only");
        assert_eq!(g.nearest(9.0, 8.0).id, "c");
        assert_eq!(g.nearest(0.9, 0.8).id, "e");
    }

    #[test]
    fn bad_graphs_are_refused_with_the_reason() {
        for (text, why) in [
            (r#"{"nodes": []}"#, "no nodes"),
            (
                r#"{"nodes": [{"id": "a", "x": 0, "y": 0}, {"id": "a", "x": 1, "y": 0}]}"#,
                "twice",
            ),
            (
                r#"{"nodes": [{"id": "a", "x": 0, "y": 0}], "edges": [["a", "z"]]}"#,
                "not in the graph",
            ),
            (
                r#"{"nodes": [{"id": "a", "x": 0, "y": 0}], "extra": 1}"#,
                "unknown field",
            ),
        ] {
            let e = Graph::parse(text).unwrap_err();
            assert!(e.contains(why), "{e}");
        }
    }
}
