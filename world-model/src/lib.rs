//! What robots and their world are made of, shared by muster's simulator
//! (`muster-sim-world`) and the robot systems that drive robots (`muster-robots`):
//! poses and differential-drive kinematics ([`kinematics`]), occupancy maps in the ROS
//! map_server format with exact ray casts and clearance ([`map`]), and the beacon colours
//! a camera tells apart ([`Colour`]). A robot system takes these, never the simulator's
//! own types, so it drives a simulated robot and a ROS 2 robot alike.

mod colour;
pub mod kinematics;
pub mod map;
mod walls;

pub use colour::Colour;
pub use kinematics::{wrap, Pose};
pub use map::OccupancyMap;
