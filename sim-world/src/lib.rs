//! muster's simulator: one process runs every robot's kinematics and sensors, and the
//! people they track, in a 2-D building. [`world::World::step`] is the whole simulation,
//! with no I/O; the `muster sim` process publishes it in shared memory.

pub mod bench;
pub mod bodies;
pub mod people;
pub mod render;
pub mod scenario;
pub mod sensors;
pub mod shm;
pub mod world;

// The world model the simulator shares with the robot systems, where it always was.
pub use muster_world_model::{kinematics, map};
