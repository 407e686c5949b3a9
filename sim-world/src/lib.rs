//! muster's simulator: one process runs every robot's kinematics and sensors, and the
//! people they track, in a 2-D building. [`world::World::step`] is the whole simulation,
//! with no I/O; the `muster sim` process publishes it in shared memory.

pub mod bench;
pub mod bodies;
pub mod kinematics;
pub mod map;
pub mod people;
pub mod render;
pub mod scenario;
pub mod sensors;
pub mod shm;
mod walls;
pub mod world;
