//! The ROS 2 messages muster speaks, as serde structs whose field order is the message
//! definition's (CDR encodes a struct as its fields in order, so these are the wire
//! layout). Checked against the ROS 2 Kilted definitions (`share/<pkg>/msg/*.msg` of
//! the `ros-kilted-*` wheels); `sensor_msgs/Range` has Kilted's `variance` field.

pub use ros2_client::builtin_interfaces::Time;
use serde::{Deserialize, Serialize};

/// A ROS message held as its CDR bytes (with the encapsulation header), published by
/// walking its definition (an open payload a command service puts on a topic).
pub struct RawMsg {
    /// The message's definition.
    pub defs: std::sync::Arc<muster_shared::ros2msg::Definitions>,
    /// The sample.
    pub data: Vec<u8>,
}

impl Serialize for RawMsg {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        self.defs.reserialize(&self.data, s)
    }
}

/// A ROS time from simulated seconds (negative and non-finite times become 0).
pub fn sim_time(seconds: f64) -> Time {
    let nanos = if seconds.is_finite() && seconds > 0.0 {
        (seconds * 1e9).min(i64::MAX as f64) as i64
    } else {
        0
    };
    Time::from_nanos(nanos)
}

/// `builtin_interfaces/Duration`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct RosDuration {
    /// Whole seconds.
    pub sec: i32,
    /// Nanoseconds, 0..1e9.
    pub nanosec: u32,
}

/// `std_msgs/Header`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Header {
    /// When the data was taken.
    pub stamp: Time,
    /// The frame the data is in.
    pub frame_id: String,
}

impl Header {
    /// A header at `seconds` (sim time) in `frame`.
    pub fn at(seconds: f64, frame: &str) -> Self {
        Header {
            stamp: sim_time(seconds),
            frame_id: frame.to_string(),
        }
    }
}

/// `rosgraph_msgs/Clock`: the simulated time, for nodes with `use_sim_time`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Clock {
    /// Now.
    pub clock: Time,
}

/// `sensor_msgs/LaserScan`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LaserScan {
    /// Stamp: the scan's time; frame: the laser's.
    pub header: Header,
    /// First beam's angle, rad (counter-clockwise, 0 ahead).
    pub angle_min: f32,
    /// Last beam's angle, rad.
    pub angle_max: f32,
    /// Angle between beams, rad.
    pub angle_increment: f32,
    /// Time between beams, s.
    pub time_increment: f32,
    /// Time between scans, s.
    pub scan_time: f32,
    /// Nearest range the laser reports, m.
    pub range_min: f32,
    /// Farthest range, m; a beam with no return reads +inf (REP 117).
    pub range_max: f32,
    /// Ranges, m, from `angle_min` to `angle_max`.
    pub ranges: Vec<f32>,
    /// Intensities (none).
    pub intensities: Vec<f32>,
}

/// `sensor_msgs/Range`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Range {
    /// Stamp and the transducer's frame.
    pub header: Header,
    /// 0 ultrasound, 1 infrared.
    pub radiation_type: u8,
    /// Cone width, rad.
    pub field_of_view: f32,
    /// Nearest range, m.
    pub min_range: f32,
    /// Farthest range, m; no echo reads +inf.
    pub max_range: f32,
    /// The reading, m.
    pub range: f32,
    /// Variance of the reading, m² (0: unknown).
    pub variance: f32,
}

/// `sensor_msgs/Range` radiation type of a sonar.
pub const ULTRASOUND: u8 = 0;

/// `geometry_msgs/Vector3` (also `Point`, which has the same fields).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Vector3 {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
}

/// `geometry_msgs/Point`.
pub type Point = Vector3;

/// `geometry_msgs/Vector3Stamped` (a camera's pan, tilt and zoom, on `ptz`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Vector3Stamped {
    /// Stamp and frame.
    pub header: Header,
    /// The vector.
    pub vector: Vector3,
}

/// `geometry_msgs/Quaternion`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Quaternion {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
    /// w.
    pub w: f64,
}

impl Quaternion {
    /// A rotation by `yaw` radians about z.
    pub fn from_yaw(yaw: f64) -> Self {
        Quaternion {
            x: 0.0,
            y: 0.0,
            z: (yaw / 2.0).sin(),
            w: (yaw / 2.0).cos(),
        }
    }

    /// The rotation's angle about z (the yaw), rad in (-π, π].
    pub fn yaw(&self) -> f64 {
        (2.0 * (self.w * self.z + self.x * self.y))
            .atan2(1.0 - 2.0 * (self.y * self.y + self.z * self.z))
    }
}

impl Default for Quaternion {
    fn default() -> Self {
        Quaternion::from_yaw(0.0)
    }
}

/// `geometry_msgs/Pose`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    /// Position, m.
    pub position: Point,
    /// Orientation.
    pub orientation: Quaternion,
}

impl Pose {
    /// A pose on the floor: x, y (m) and heading (rad).
    pub fn planar(x: f64, y: f64, theta: f64) -> Self {
        Pose {
            position: Point { x, y, z: 0.0 },
            orientation: Quaternion::from_yaw(theta),
        }
    }
}

/// A 6×6 covariance, row-major (serde handles fixed arrays only up to 32 long).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Covariance(pub [f64; 36]);

impl Covariance {
    /// A diagonal covariance.
    pub fn diagonal(d: [f64; 6]) -> Self {
        let mut c = [0.0; 36];
        for (k, v) in d.into_iter().enumerate() {
            c[k * 7] = v;
        }
        Covariance(c)
    }
}

impl Serialize for Covariance {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        use serde::ser::SerializeTuple;
        let mut t = s.serialize_tuple(36)?;
        for v in &self.0 {
            t.serialize_element(v)?;
        }
        t.end()
    }
}

impl<'de> Deserialize<'de> for Covariance {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl<'de> serde::de::Visitor<'de> for V {
            type Value = Covariance;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("36 float64")
            }
            fn visit_seq<A: serde::de::SeqAccess<'de>>(
                self,
                mut a: A,
            ) -> Result<Covariance, A::Error> {
                let mut c = [0.0; 36];
                for (k, v) in c.iter_mut().enumerate() {
                    *v = a
                        .next_element()?
                        .ok_or_else(|| serde::de::Error::invalid_length(k, &self))?;
                }
                Ok(Covariance(c))
            }
        }
        d.deserialize_tuple(36, V)
    }
}

/// `geometry_msgs/PoseWithCovariance`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseWithCovariance {
    /// The pose.
    pub pose: Pose,
    /// Its covariance (x, y, z, rotations about x, y, z).
    pub covariance: Covariance,
}

/// `geometry_msgs/Twist`: a velocity command or a measured velocity.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Twist {
    /// Linear velocity, m/s (x ahead).
    pub linear: Vector3,
    /// Angular velocity, rad/s (z counter-clockwise).
    pub angular: Vector3,
}

/// `geometry_msgs/TwistWithCovariance`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TwistWithCovariance {
    /// The velocity.
    pub twist: Twist,
    /// Its covariance.
    pub covariance: Covariance,
}

/// `nav_msgs/Odometry`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Odometry {
    /// Stamp; frame: the odometry frame.
    pub header: Header,
    /// The robot's frame (the twist is in it).
    pub child_frame_id: String,
    /// Pose in the odometry frame.
    pub pose: PoseWithCovariance,
    /// Velocity in the robot's frame.
    pub twist: TwistWithCovariance,
}

/// `geometry_msgs/PoseStamped`: a goal (`/goal_pose`) or a pose.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseStamped {
    /// Stamp and frame.
    pub header: Header,
    /// The pose.
    pub pose: Pose,
}

/// `geometry_msgs/PoseWithCovarianceStamped` (AMCL's `amcl_pose`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseWithCovarianceStamped {
    /// Stamp and frame.
    pub header: Header,
    /// The pose and its covariance.
    pub pose: PoseWithCovariance,
}

/// `geometry_msgs/Pose2D`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Pose2D {
    /// x, m.
    pub x: f64,
    /// y, m.
    pub y: f64,
    /// Heading, rad.
    pub theta: f64,
}

/// `std_msgs/String`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StringMsg {
    /// The text.
    pub data: String,
}

macro_rules! std_value {
    ($($(#[$doc:meta])* $name:ident($t:ty);)*) => {$(
        $(#[$doc])*
        #[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
        pub struct $name {
            /// The value.
            pub data: $t,
        }
    )*};
}
std_value! {
    /// `std_msgs/Float64`.
    Float64(f64);
    /// `std_msgs/Float32`.
    Float32(f32);
    /// `std_msgs/Int32`.
    Int32(i32);
    /// `std_msgs/Int64`.
    Int64(i64);
    /// `std_msgs/Bool`.
    Bool(bool);
}

/// `nav_msgs/MapMetaData`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MapMetaData {
    /// When the map was loaded.
    pub map_load_time: Time,
    /// Cell size, m.
    pub resolution: f32,
    /// Cells along x.
    pub width: u32,
    /// Cells along y.
    pub height: u32,
    /// Cell (0, 0)'s corner in the map frame.
    pub origin: Pose,
}

/// `nav_msgs/OccupancyGrid`: row-major from cell (0, 0), 0 free, 100 occupied, -1 unknown.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct OccupancyGrid {
    /// Stamp and the map frame.
    pub header: Header,
    /// Size, resolution, origin.
    pub info: MapMetaData,
    /// Occupancy per cell.
    pub data: Vec<i8>,
}

/// `std_msgs/ColorRGBA`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ColorRgba {
    /// Red, 0..1.
    pub r: f32,
    /// Green, 0..1.
    pub g: f32,
    /// Blue, 0..1.
    pub b: f32,
    /// Opacity, 0..1.
    pub a: f32,
}

/// `sensor_msgs/CompressedImage` (a marker's texture; muster sends none).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CompressedImage {
    /// Stamp and frame.
    pub header: Header,
    /// Image format.
    pub format: String,
    /// Image bytes.
    pub data: Vec<u8>,
}

impl Default for Header {
    fn default() -> Self {
        Header::at(0.0, "")
    }
}

/// `visualization_msgs/UVCoordinate`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct UvCoordinate {
    /// u.
    pub u: f32,
    /// v.
    pub v: f32,
}

/// `visualization_msgs/MeshFile`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct MeshFile {
    /// File name.
    pub filename: String,
    /// File bytes.
    pub data: Vec<u8>,
}

/// `visualization_msgs/Marker` (Kilted's fields).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Marker {
    /// Stamp and frame.
    pub header: Header,
    /// Namespace: with `id`, the marker's identity.
    pub ns: String,
    /// Id within the namespace.
    pub id: i32,
    /// Shape ([`Marker::CYLINDER`], ...).
    #[serde(rename = "type")]
    pub kind: i32,
    /// Add, delete, ...
    pub action: i32,
    /// Where.
    pub pose: Pose,
    /// Size, m.
    pub scale: Vector3,
    /// Colour.
    pub color: ColorRgba,
    /// How long it stays (0: until replaced).
    pub lifetime: RosDuration,
    /// Whether it moves with its frame.
    pub frame_locked: bool,
    /// Points (line and list shapes).
    pub points: Vec<Point>,
    /// Per-point colours.
    pub colors: Vec<ColorRgba>,
    /// Texture resource.
    pub texture_resource: String,
    /// Texture.
    pub texture: CompressedImage,
    /// Texture coordinates.
    pub uv_coordinates: Vec<UvCoordinate>,
    /// Text of a text marker.
    pub text: String,
    /// Mesh resource.
    pub mesh_resource: String,
    /// Mesh file.
    pub mesh_file: MeshFile,
    /// Whether a mesh uses its own materials.
    pub mesh_use_embedded_materials: bool,
}

impl Marker {
    /// Shape: a sphere.
    pub const SPHERE: i32 = 2;
    /// Shape: a cylinder.
    pub const CYLINDER: i32 = 3;
    /// Shape: camera-facing text.
    pub const TEXT_VIEW_FACING: i32 = 9;
    /// Action: add or replace.
    pub const ADD: i32 = 0;
}

/// `visualization_msgs/MarkerArray`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct MarkerArray {
    /// The markers.
    pub markers: Vec<Marker>,
}

/// `geometry_msgs/Transform`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Transform {
    /// Translation, m.
    pub translation: Vector3,
    /// Rotation.
    pub rotation: Quaternion,
}

/// `geometry_msgs/TransformStamped`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TransformStamped {
    /// Stamp; frame: the parent frame.
    pub header: Header,
    /// The child frame.
    pub child_frame_id: String,
    /// The child frame's pose in the parent.
    pub transform: Transform,
}

/// `tf2_msgs/TFMessage` (`/tf`, `/tf_static`).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TfMessage {
    /// The transforms.
    pub transforms: Vec<TransformStamped>,
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn cdr<T: Serialize>(v: &T) -> Vec<u8> {
        cdr_encoding::to_vec::<T, byteorder::LittleEndian>(v).unwrap()
    }

    #[test]
    fn a_clock_is_seconds_and_nanoseconds() {
        // builtin_interfaces/Time: int32 sec, uint32 nanosec.
        let b = cdr(&Clock {
            clock: sim_time(12.25),
        });
        assert_eq!(b, [12, 0, 0, 0, 0x80, 0xb2, 0xe6, 0x0e]);
        assert_eq!(sim_time(-1.0), Time::ZERO);
        assert_eq!(sim_time(f64::NAN), Time::ZERO);
    }

    #[test]
    fn a_covariance_is_36_doubles_without_a_length() {
        let b = cdr(&Covariance::diagonal([1.0, 2.0, 3.0, 4.0, 5.0, 6.0]));
        assert_eq!(b.len(), 36 * 8);
        assert_eq!(f64::from_le_bytes(b[7 * 8..8 * 8].try_into().unwrap()), 2.0);
        let back: Covariance = cdr_encoding::from_bytes::<Covariance, byteorder::LittleEndian>(&b)
            .unwrap()
            .0;
        assert_eq!(back, Covariance::diagonal([1.0, 2.0, 3.0, 4.0, 5.0, 6.0]));
    }

    #[test]
    fn a_laser_scan_is_laid_out_as_the_message() {
        let scan = LaserScan {
            header: Header::at(1.5, "T1/base_link"),
            angle_min: -1.0,
            angle_max: 1.0,
            angle_increment: 0.5,
            time_increment: 0.0,
            scan_time: 0.1,
            range_min: 0.0,
            range_max: 8.0,
            ranges: vec![1.0, 2.0, 3.0, 4.0, 5.0],
            intensities: vec![],
        };
        let b = cdr(&scan);
        // sec, nanosec, then the frame id: length with its NUL, bytes, NUL, padding to 4.
        assert_eq!(&b[..8], &[1, 0, 0, 0, 0x00, 0x65, 0xcd, 0x1d]);
        assert_eq!(u32::from_le_bytes(b[8..12].try_into().unwrap()), 13);
        assert_eq!(&b[12..24], b"T1/base_link");
        assert_eq!(b[24], 0);
        // 7 floats from offset 28 (after 3 bytes of padding), then 5 ranges.
        assert_eq!(f32::from_le_bytes(b[28..32].try_into().unwrap()), -1.0);
        assert_eq!(u32::from_le_bytes(b[56..60].try_into().unwrap()), 5);
        assert_eq!(f32::from_le_bytes(b[60..64].try_into().unwrap()), 1.0);
        assert_eq!(b.len(), 60 + 5 * 4 + 4);
        let back: LaserScan = cdr_encoding::from_bytes::<LaserScan, byteorder::LittleEndian>(&b)
            .unwrap()
            .0;
        assert_eq!(back, scan);
    }

    #[test]
    fn yaw_round_trips_through_a_quaternion() {
        for yaw in [-3.0, -1.0, 0.0, 0.5, 3.1] {
            assert!((Quaternion::from_yaw(yaw).yaw() - yaw).abs() < 1e-12);
        }
    }
}
