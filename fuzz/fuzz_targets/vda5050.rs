//! VDA 5050: any bytes on any topic give a message or a clear refusal, never a panic;
//! and a vehicle (`AgvCore`) fed any sequence of orders (each checked first, as the
//! vehicle checks them), instant actions, nodes reached and refused messages never
//! panics and always says a state that passes its own checks.
#![no_main]
use libfuzzer_sys::fuzz_target;
use muster_vda5050::agv::{AgvCore, AgvOptions};
use muster_vda5050::msg::{
    decode, encode, Action, BlockingType, Connection, Edge, Factsheet, Header, InstantActions,
    Node, NodePosition, Order, State, Visualization,
};

const IDS: [&str; 5] = ["a", "b", "c", "d", "e"];
const ACTIONS: [&str; 7] = [
    "startPause",
    "stopPause",
    "cancelOrder",
    "stateRequest",
    "factsheetRequest",
    "liftFork",
    "",
];

/// An order shaped by `b` (which may break the graph's rules: the checks decide).
fn order(b: &[u8]) -> Order {
    let at = |i: usize| b.get(i).copied().unwrap_or(0);
    let n = (at(0) % 5) as usize + 1;
    let mut seq = (at(1) % 8) as u32;
    let mut nodes = Vec::new();
    for i in 0..n {
        let k = at(2 + i);
        nodes.push(Node {
            node_id: IDS[(k % 5) as usize].to_string(),
            sequence_id: seq,
            node_description: None,
            released: k & 0x80 == 0,
            node_position: (k & 0x40 == 0).then(|| NodePosition {
                x: (k % 16) as f64 - 4.0,
                y: (k >> 4) as f64 * 0.5,
                theta: (k & 0x20 != 0).then_some(k as f64 * 0.1 - 6.0),
                allowed_deviation_x_y: (k & 0x10 != 0).then_some(0.3),
                allowed_deviation_theta: None,
                map_id: if k & 0x08 == 0 { "muster".into() } else { "other".into() },
                map_description: None,
            }),
            actions: if k & 0x04 != 0 {
                vec![Action {
                    action_type: "pick".into(),
                    action_id: format!("p{i}"),
                    action_description: None,
                    blocking_type: BlockingType::Hard,
                    action_parameters: vec![],
                }]
            } else {
                vec![]
            },
        });
        seq += if k & 0x02 == 0 { 2 } else { 1 };
    }
    let edges = nodes
        .windows(2)
        .enumerate()
        .filter(|(i, _)| at(8 + i) & 0x01 == 0)
        .map(|(i, w)| Edge {
            edge_id: format!("e{i}"),
            sequence_id: w[0].sequence_id + 1,
            edge_description: None,
            released: w[1].released,
            start_node_id: w[0].node_id.clone(),
            end_node_id: w[1].node_id.clone(),
            max_speed: (at(8 + i) & 0x02 != 0).then_some(at(8 + i) as f64 / 100.0),
            length: None,
            actions: vec![],
        })
        .collect();
    Order {
        header: Header::now(1, "2.0.0", "muster", "D1"),
        order_id: format!("o{}", at(13) % 3),
        order_update_id: (at(14) % 4) as u32,
        zone_set_id: None,
        nodes,
        edges,
    }
}

fuzz_target!(|data: &[u8]| {
    let Some((&pick, rest)) = data.split_first() else { return };
    if pick & 1 == 0 {
        // The bytes on every topic.
        let _ = decode::<State>(rest);
        let _ = decode::<Order>(rest);
        let _ = decode::<InstantActions>(rest);
        let _ = decode::<Connection>(rest);
        let _ = decode::<Factsheet>(rest);
        let _ = decode::<Visualization>(rest);
        return;
    }
    let mut core = AgvCore::new(&AgvOptions::new("x:1"), "D1");
    let at = (((pick >> 1) % 8) as f64 - 4.0, 0.0);
    for op in rest.chunks(16) {
        match op[0] % 4 {
            0 => {
                // Checked as the vehicle checks what comes over the wire.
                let o = order(&op[1..]);
                if let Ok(bytes) = encode(&o) {
                    if let Ok(o) = decode::<Order>(&bytes) {
                        core.order(o, at);
                    }
                }
            }
            1 => {
                let actions = op[1..]
                    .iter()
                    .take(3)
                    .enumerate()
                    .map(|(i, &k)| Action {
                        action_type: ACTIONS[(k % 7) as usize].into(),
                        action_id: format!("i{}", k % 4 + i as u8),
                        action_description: None,
                        blocking_type: BlockingType::None,
                        action_parameters: vec![],
                    })
                    .collect();
                let ia = InstantActions {
                    header: Header::now(1, "2.0.0", "muster", "D1"),
                    instant_actions: actions,
                };
                if let Ok(bytes) = encode(&ia) {
                    if let Ok(ia) = decode::<InstantActions>(&bytes) {
                        core.instant(ia);
                    }
                }
            }
            2 => core.reached(),
            _ => core.invalid_message("order", "fuzzed"),
        }
        let _ = core.target();
        let st = core.state(7, (at.0, at.1, 3.0), (0.1, 0.0));
        if let Err(e) = encode(&st) {
            panic!("the vehicle's own state breaks its checks: {e}");
        }
    }
});
