//! Command-line flags.

use clap::{Args, Parser, Subcommand};
use muster_shared::types::ServiceKind;
use std::time::Duration;

/// muster: many users, many robots, one broker, zero-copy shared memory.
#[derive(Parser, Debug)]
#[command(name = "muster", version, about)]
pub struct Cli {
    /// Instance name: prefixes everything this process creates in shared memory.
    #[arg(long, global = true, default_value = "default")]
    pub instance: String,
    /// Scenario seconds per wall second, the same on every process of an instance:
    /// broker pings and their deadline, systems' update rates, scripted users' think and
    /// hold times and the simulator follow it; infrastructure latencies stay wall time.
    /// (Default 1; `experiment scalability` defaults to 10.)
    #[arg(long, global = true)]
    pub time_scale: Option<muster_shared::clock::TimeScale>,
    /// (internal) Run in this network namespace (`/run/netns/NAME`), as `muster netns`
    /// and `muster up --hosts --netns` start brokers in theirs.
    #[arg(long, global = true, hide = true)]
    pub in_netns: Option<String>,
    /// Scheduling niceness of this process, -20 (first) to 19 (last). The broker and
    /// systems default to -5, so a host crowded with user processes still serves
    /// them first (lowering it needs root, CAP_SYS_NICE or RLIMIT_NICE; without, they
    /// keep the niceness they were started with, and say so at debug level); other
    /// commands keep theirs. `--nice 0` turns the boost off.
    #[arg(long, global = true, allow_hyphen_values = true, value_parser = clap::value_parser!(i32).range(-20..=19))]
    pub nice: Option<i32>,
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Run the broker: registry of systems and services, request arbitration, liveness.
    Broker(BrokerArgs),
    /// Run a robot system.
    #[command(subcommand)]
    System(SystemCommand),
    /// Act as a user: list, request, link, or (no verb) the interactive menu.
    User(UserArgs),
    /// Run the main job on the built-in default: a broker and synthetic systems as child
    /// processes, and a user listing, requesting, receiving data and linking.
    Up(UpArgs),
    /// Run the simulator: every robot's kinematics and sensors, and people, published in
    /// shared memory. Also renders a picture, exports the map, or benchmarks.
    Sim(SimArgs),
    /// The simulator's robots (or ROS 2 robots, `--ros2`) as VDA 5050 vehicles over
    /// MQTT, driven by any master control: orders driven node by node with the delivery
    /// robot's planner and safety; state, visualization, connection (last will) and
    /// factsheet published; instant actions answered.
    Agv(AgvArgs),
    /// Benchmarks that print figures.
    #[command(subcommand)]
    Bench(BenchCommand),
    /// Stress: a broker, synthetic systems and N separate scripted user processes;
    /// latency histograms from the users' and the broker's side, the floor measured in
    /// the same run, and checks (every user got a list, every request answered, no
    /// quota exceeded as the systems counted it).
    Stress(StressArgs),
    /// Predict utilisation and response times as users grow, from stress reports: a
    /// broker M/G/1 queue plus processor sharing on the cores, calibrated on the lightest
    /// report; prints predicted against measured for every report given.
    Capacity(CapacityArgs),
    /// The paper's experiments, reproduced on the simulator with reports.
    #[command(subcommand)]
    Experiment(ExperimentCommand),
    /// Make a key pair for a remote user (or the broker) and print the line to add to
    /// the broker's access file.
    Keygen(KeygenArgs),
    /// Make the certificates of a federation's hosts for mutual TLS (`muster broker
    /// --federate --tls DIR`): a certificate authority (made once, kept in DIR) and a
    /// key and certificate per host, named after the host.
    Certs(CertsArgs),
    /// Follow the broker's event feed: registrations, removals (with why), users joining
    /// and leaving, requests, queueing, grants, refusals (with the reason), sessions
    /// ending, withdrawals, links; one JSON object a line, the feed's recent history
    /// first.
    Events(EventsArgs),
    /// Record the world (map, robots, laser scans, people, camera detections) and the
    /// infrastructure (the broker's events, the service list) into an MCAP file, on
    /// Foxglove's schemas where one fits; open it in Foxglove or read it with any MCAP
    /// reader.
    Record(RecordArgs),
    /// An operator's actions (the instance owner's processes only): the broker's status
    /// (systems and their liveness, users, sessions, queues), withdraw or restore a
    /// service, end a session, drop a user, move or drop a queued request.
    Operator(OperatorArgs),
    /// The operator's full-screen console: services, systems and their liveness, users,
    /// sessions, task queues and the broker's events, live; keys to withdraw or restore
    /// a service, end a session, drop a user, move or drop a queued request.
    Console(ConsoleArgs),
    /// The web console: an HTTP and WebSocket server with the app inside the binary.
    /// People sign in with the access file's `web` lines (`muster keygen --web`) and
    /// list, request, watch, drive and link services as their patterns allow.
    Web(WebArgs),
    /// Serve the live world and infrastructure (the topics of `muster record`) over the
    /// Foxglove WebSocket protocol, for Foxglove or Lichtblick.
    View(ViewArgs),
    /// Serve a recording (`muster record`) over the Foxglove WebSocket protocol again, at
    /// its own pace or `--speed` times it.
    Replay(ReplayArgs),
    /// Hosts in network namespaces on this machine (root): one namespace per host, each
    /// joined to the others only through a TCP proxy per pair of hosts that adds delay
    /// and loss; prints each host's addresses and `muster broker` flags, and keeps the
    /// namespaces until stopped. Stop a pair's proxy (SIGSTOP) to cut the link between
    /// two hosts.
    Netns(NetnsArgs),
    /// (internal) A TCP relay that delays what it passes and stalls it now and then as
    /// loss stalls a TCP stream (used between the hosts of `muster netns`).
    #[command(hide = true)]
    NetProxy(NetProxyArgs),
    /// Remove what killed processes left in shared memory (/dev/shm): their iceoryx2
    /// nodes, ports and segments (those of `--pid`, or all), and the instance's fence
    /// file once no broker or standby of it runs. A broker runs it too, as a process of
    /// its own, so that a cleanup outlives a broker killed in the middle of it (iceoryx2
    /// never cleans a node whose cleaner died).
    Cleanup {
        /// Only this process's, once it has exited (a process SIGKILLed while stopped
        /// takes a moment to go; until then its nodes are not dead).
        #[arg(long)]
        pid: Option<u32>,
        /// Wait this long first.
        #[arg(long, default_value = "0s", value_parser = duration)]
        after: Duration,
        /// (internal) Run by a broker: its instance's fence is never removed (a broker
        /// starting or a standby taking over may be about to hold it).
        #[arg(long, hide = true)]
        beside_broker: bool,
    },
}

#[derive(Subcommand, Debug)]
pub enum ExperimentCommand {
    /// Experiment 2: a user links the red tracker into the delivery robot, which follows
    /// the person (T3 mobile makes the convoy). Writes report.json, figure3.png and
    /// distance.png.
    Link(ExperimentLinkArgs),
    /// Experiment 1: stationary trackers T1-T3, the delivery robot wearing the red
    /// beacon, and scripted users arriving and leaving over the run, listing, requesting
    /// and ending services and tasking the robot. Writes Tables 1-2, figure4.png,
    /// report.json and report.md (beside the paper's figures).
    Scalability(ExperimentScalabilityArgs),
}

#[derive(Args, Debug)]
pub struct ExperimentScalabilityArgs {
    /// Scripted user processes over the run.
    #[arg(long, default_value_t = 10)]
    pub users: usize,
    /// Length of the run, scenario minutes.
    #[arg(long, default_value_t = 50.0)]
    pub minutes: f64,
    /// Folder for the report.
    #[arg(long, default_value = "experiment-scalability")]
    pub report: std::path::PathBuf,
    /// Seed of the simulator, the filters and the users.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Mean pause between a user's interactions (scenario time).
    #[arg(long, default_value = "5m", value_parser = duration)]
    pub think: Duration,
    /// Shortest and longest time a user holds a session (scenario time; the paper's
    /// tracking sessions ran 25 minutes at the median).
    #[arg(long, default_value = "5m", value_parser = duration)]
    pub hold_min: Duration,
    /// See `--hold-min`.
    #[arg(long, default_value = "35m", value_parser = duration)]
    pub hold_max: Duration,
    /// Mean time between a user's list refreshes (scenario time).
    #[arg(long, default_value = "10m", value_parser = duration)]
    pub refresh: Duration,
    /// Stationary tracking robots (the paper: 3). Beyond three, each further three are
    /// one more tracking system (`tracking-2`, ...) with its own red, green and blue
    /// services, standing along the corridors.
    #[arg(long, default_value_t = 3)]
    pub trackers: usize,
    /// Delivery robots (the paper: 1), each its own system (`delivery-2`, ...) starting in
    /// an office, its home.
    #[arg(long, default_value_t = 1)]
    pub deliveries: usize,
    /// Show the processes' logs.
    #[arg(long)]
    pub verbose: bool,
}

#[derive(Args, Debug)]
pub struct ExperimentLinkArgs {
    /// Simulator speed: sim seconds per wall second (every process follows its clock).
    #[arg(long, default_value_t = 10.0)]
    pub speed: f64,
    /// Length of the run in sim time.
    #[arg(long, default_value = "10m", value_parser = duration)]
    pub duration: Duration,
    /// Folder for the report.
    #[arg(long, default_value = "experiment-link")]
    pub report: std::path::PathBuf,
    /// Seed of the simulator and the filters.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// People beside the paper's three, walking from office to office across the
    /// robots' ways (a crowd; at most one per office, 16). Their beacons are colours no
    /// tracking service offers.
    #[arg(long, default_value_t = 0)]
    pub crowd: usize,
    /// Show the processes' logs.
    #[arg(long)]
    pub verbose: bool,
}

#[derive(Args, Debug)]
pub struct CapacityArgs {
    /// Stress reports (`report.json` files or the folders holding them), any loads.
    pub reports: Vec<std::path::PathBuf>,
    /// Further user counts to predict.
    #[arg(long, value_delimiter = ',', default_value = "100,300,900,2000,5000")]
    pub users: Vec<u64>,
    /// Cores (default: this machine's).
    #[arg(long)]
    pub cores: Option<f64>,
    /// One JSON object instead of a table.
    #[arg(long)]
    pub json: bool,
}

#[derive(Args, Debug)]
pub struct KeygenArgs {
    /// The user's name (1 to 24 of [A-Za-z0-9_-]); the key file is DIR/NAME.key.
    #[arg(long, required_unless_present = "broker", conflicts_with = "broker")]
    pub user: Option<String>,
    /// Make the broker's key instead (DIR/broker.key; give it to `muster broker --key`).
    #[arg(long)]
    pub broker: bool,
    /// Folder to write the key file into (created if missing).
    #[arg(long, default_value = ".")]
    pub out: std::path::PathBuf,
    /// Service patterns the printed access line allows (globs over `system/service`,
    /// e.g. `T1/*`); none prints a line that lets the user connect but see nothing.
    #[arg(long = "allow")]
    pub allow: Vec<String>,
    /// Print an `operator` line: the user may also act as an operator (`muster operator`,
    /// `muster console --remote`).
    #[arg(long, conflicts_with = "broker")]
    pub operator: bool,
    /// Also make a web token for `muster web`: written to DIR/NAME.web (mode 600), its
    /// hash printed as a `web NAME HASH` line after the access line.
    #[arg(long, conflicts_with = "broker")]
    pub web: bool,
}

/// How a user reaches a broker over UDP (all user verbs).
#[derive(Args, Debug, Clone)]
pub struct RemoteArgs {
    /// Connect to this broker's UDP front (`--udp` of `muster broker`) instead of shared
    /// memory.
    #[arg(long, global = true, requires = "key")]
    pub remote: Option<std::net::SocketAddr>,
    /// The user's key file (from `muster keygen --user NAME`).
    #[arg(long, global = true)]
    pub key: Option<std::path::PathBuf>,
    /// Refuse a broker whose public key is not this (64 hex digits, printed by the broker
    /// and by `muster keygen --broker`).
    #[arg(long, global = true)]
    pub broker_key: Option<String>,
    /// (testing) Seeded faults on this user's datagrams: `loss=0.05,dup=0.01,reorder=0.02,seed=7`.
    #[arg(long, global = true, hide = true)]
    pub faults: Option<muster_users::Faults>,
}

#[derive(Subcommand, Debug)]
pub enum BenchCommand {
    /// Connect N separate user processes to a broker serving S services; report setup
    /// time, shared memory, broker RSS and idle CPU, per-user PSS, request and list latency.
    Scale(ScaleArgs),
    /// Time failure detection: SIGKILL of a system until it leaves the list, and SIGKILL
    /// plus restart of the broker until the whole list is back.
    Liveness(LivenessArgs),
    /// The floor: raw round trips between this process and an echo process through the
    /// same iceoryx2 inbox + bell wake-up that muster's messages use.
    Floor(FloorArgs),
    /// The UDP path: raw UDP round trip (floor), remote list and service request with
    /// their ratio to it, completion and duplicate grants under seeded loss, duplication
    /// and reordering, and the same under a flood of hostile datagrams.
    Remote(RemoteBenchArgs),
    /// Broker redundancy: SIGKILL or SIGSTOP the primary again and again under users
    /// holding data sessions and users making requests, a standby taking over each time;
    /// time from the signal to the first new grant, the whole list and the new primary
    /// serving; lost sessions, sequence gaps, duplicate grants, quota left counted in use
    /// and files left in /dev/shm.
    Failover(FailoverArgs),
    /// Hosts federated over Zenoh (three on loopback): the raw Zenoh round trip (floor),
    /// cross-host service request and its ratio to the floor beside a local one, list
    /// propagation between hosts, session update latency across hosts and locally;
    /// then the same with N users per host holding sessions on other hosts.
    Federation(FederationBenchArgs),
    /// ROS 2 against rclpy (the ROS 2 Kilted wheels): an rclpy publisher to a muster user
    /// through `muster system ros2` beside rclpy to rclpy, a muster goal to an rclpy
    /// subscriber, and `muster sim --ros2` with N robots and one rclpy node on every scan.
    Ros2(Ros2BenchArgs),
    /// The web console under many viewers: N WebSocket clients (Python `websockets`)
    /// signed in as N users, each watching the list and one data session at 10 Hz;
    /// update latency from the system's send to the client's receive beside a shared
    /// memory user's in the same run, the web process's CPU and memory, updates lost,
    /// and the broker's request latency before and while they watch.
    Web(WebBenchArgs),
    /// VDA 5050 fleets: N virtual vehicles (vda-5050-lib, state at 1 Hz) behind `muster
    /// system vda5050`, N muster users each holding one and giving it goals; order →
    /// the vehicle's acknowledging state against a raw MQTT publish → subscribe round
    /// trip through the same mosquitto, in the same run; CPU of mosquitto, the bridge,
    /// the vehicles' process and the broker.
    Vda5050(Vda5050BenchArgs),
    /// Every kind of process (broker, standby, system, user, simulator, federated
    /// broker) SIGKILLed N times each on an instance of its own; then the files in
    /// /dev/shm left after the instance's next start and after `muster cleanup`. Run
    /// it alone on the host.
    Leftovers(LeftoversArgs),
    /// The service list at a size (default 10,000 services), in shared memory: a page
    /// read in place, pages through filters, the whole list read unchanged and after a
    /// change, and the broker's side of one change.
    List(ListBenchArgs),
    /// (internal) A user of `bench failover`.
    #[command(hide = true)]
    FailoverUser(FailoverUserArgs),
    /// (internal) The echo process of `bench remote`'s UDP floor.
    #[command(hide = true)]
    UdpEcho,
    /// (internal) The echo process of `bench federation`'s Zenoh floor: a Zenoh peer
    /// listening on this loopback port.
    #[command(hide = true)]
    ZenohEcho {
        /// The port.
        port: u16,
    },
    /// (internal) The echo process of `bench floor`.
    #[command(hide = true)]
    Echo,
}

#[derive(Args, Debug)]
pub struct RemoteBenchArgs {
    /// Raw UDP round trips and list requests to time.
    #[arg(long, default_value_t = 2000)]
    pub round_trips: usize,
    /// Service requests per row (clean, each fault level, flood).
    #[arg(long, default_value_t = 500)]
    pub requests: usize,
    /// Fault levels in percent: each is that much loss, duplication and reordering.
    #[arg(long, value_delimiter = ',', default_value = "1,5,20")]
    pub faults: Vec<f64>,
    /// Slow-link rows: round trips added on the user's side (5 % loss on each), e.g.
    /// `300ms,1s`; empty for none.
    #[arg(long, value_delimiter = ',', default_value = "300ms,1s")]
    pub slow: Vec<humantime::Duration>,
    /// Handshakes per second from one address (each with a valid token and a Noise
    /// message, costing the broker a Diffie-Hellman and a pending slot) while real users
    /// log in (0: no handshake-flood row).
    #[arg(long, default_value_t = 400)]
    pub handshake_flood: u64,
    /// Hostile datagrams per second during the flood row (0: no flood row).
    #[arg(long, default_value_t = 20000)]
    pub flood_rate: u64,
    /// Loopback source addresses the flood comes from.
    #[arg(long, default_value_t = 500)]
    pub flood_sources: usize,
    /// Print one JSON object instead of a table.
    #[arg(long)]
    pub json: bool,
}

/// What the link between two hosts does to their traffic.
#[derive(Args, Debug, Clone, Copy)]
pub struct LinkArgs {
    /// One-way delay each proxy adds (the round trip grows by twice this).
    #[arg(long, default_value = "0s", value_parser = duration)]
    pub delay: Duration,
    /// Loss, percent of the proxy's reads: a lost one (and what follows it, in order)
    /// waits a further 200 ms, as a TCP stream waits for a retransmission.
    #[arg(long, default_value_t = 0.0)]
    pub loss: f64,
    /// Seed of the loss draws.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
}

#[derive(Args, Debug)]
pub struct RecordArgs {
    /// The file (default: muster-INSTANCE.mcap here).
    #[arg(long)]
    pub out: Option<std::path::PathBuf>,
    /// Stop by itself after this long (default: run until Ctrl-C).
    #[arg(long, value_parser = duration)]
    pub duration: Option<Duration>,
    #[command(flatten)]
    pub scene: SceneArgs,
}

/// The world a recorder or viewer draws: the simulator's own flags.
#[derive(Args, Debug)]
pub struct SceneArgs {
    /// The simulator's scenario (for the map and the robots' sensors), as given to
    /// `muster sim`; default the paper's.
    #[arg(long)]
    pub scenario: Option<std::path::PathBuf>,
    /// The simulator's map, as given to `muster sim --map`.
    #[arg(long)]
    pub map: Option<std::path::PathBuf>,
    /// Also request this service (repeatable) and write its updates on
    /// `/muster/services/ID` with their schema (an open type's own: a ROS 2 message as
    /// `cdr` with its `ros2msg` definition).
    #[arg(long = "service")]
    pub services: Vec<String>,
}

#[derive(Args, Debug)]
pub struct WebArgs {
    /// Where to listen (port 0: any free port; the address is printed as JSON).
    #[arg(long, default_value = "127.0.0.1:8080")]
    pub listen: std::net::SocketAddr,
    /// The access file (`muster keygen --user NAME --web [--allow PATTERN]`): who may
    /// sign in, and which services each may see and use. Re-read when it changes.
    #[arg(long)]
    pub access: std::path::PathBuf,
    /// How long a signing-in user's connection waits for a broker.
    #[arg(long, default_value = "5s", value_parser = duration)]
    pub wait: Duration,
    /// The floor's map for the map page (ROS map_server YAML, as the simulator's
    /// `--map`); default: the simulator's office.
    #[arg(long)]
    pub map: Option<std::path::PathBuf>,
    /// Serve HTTPS: a certificate chain and its private key, PEM files (session
    /// cookies are then `Secure`).
    #[arg(long, num_args = 2, value_names = ["CERT", "KEY"])]
    pub tls: Option<Vec<std::path::PathBuf>>,
}

#[derive(Args, Debug)]
pub struct ConsoleArgs {
    /// How long to wait for a broker.
    #[arg(long, default_value = "5s", value_parser = duration)]
    pub wait: Duration,
    /// `--remote ADDR --key FILE`: an operator over UDP (an `operator` line in the
    /// broker's access file); the event log then comes over the same connection.
    #[command(flatten)]
    pub remote: RemoteArgs,
    /// The services pane shows this part of the list.
    #[command(flatten)]
    pub list: ListFilterArgs,
}

#[derive(Args, Debug)]
pub struct OperatorArgs {
    /// How long to wait for a broker.
    #[arg(long, default_value = "5s", value_parser = duration, global = true)]
    pub wait: Duration,
    /// One JSON object instead of text.
    #[arg(long, global = true)]
    pub json: bool,
    #[command(flatten)]
    pub remote: RemoteArgs,
    #[command(subcommand)]
    pub action: OperatorAction,
}

#[derive(Subcommand, Debug)]
pub enum OperatorAction {
    /// Systems (liveness: last answer to a ping, delinquencies), users, sessions, queues.
    Status,
    /// Withdraw a service (its queue is refused).
    Withdraw {
        /// The service (`system/name`).
        service: String,
    },
    /// Offer a withdrawn service again.
    Restore {
        /// The service.
        service: String,
    },
    /// End a session (its system ends it; its user hears why).
    End {
        /// The session (16 hex digits, as users and `status` print it).
        session: String,
    },
    /// Drop a user: its sessions end, its requests and links go.
    DropUser {
        /// The user's id.
        user: String,
    },
    /// Move a queued request to a place in its service's task queue (1 = next).
    Move {
        /// The service.
        service: String,
        /// The request's user.
        user: String,
        /// Its request number.
        req: u64,
        /// Its new place.
        position: u16,
    },
    /// Drop a queued request (its user is told).
    DropRequest {
        /// The service.
        service: String,
        /// The request's user.
        user: String,
        /// Its request number.
        req: u64,
    },
}

#[derive(Args, Debug)]
pub struct ViewArgs {
    /// Where to serve (port 0: any free port; the address is printed as JSON).
    #[arg(long, default_value = "127.0.0.1:8765")]
    pub listen: std::net::SocketAddr,
    /// Most viewers at once (one more is refused with 503).
    #[arg(long, default_value_t = 32, value_parser = clap::value_parser!(u16).range(1..=1024))]
    pub max_clients: u16,
    /// The operators' token for the event feed (`ws://ADDR/events?token=T`), the file's
    /// first line (default: a new random one, printed at start).
    #[arg(long)]
    pub token_file: Option<std::path::PathBuf>,
    /// Stop by itself after this long (default: run until Ctrl-C).
    #[arg(long, value_parser = duration)]
    pub duration: Option<Duration>,
    #[command(flatten)]
    pub scene: SceneArgs,
}

#[derive(Args, Debug)]
pub struct ReplayArgs {
    /// The recording.
    pub file: std::path::PathBuf,
    /// Times the recording's own pace.
    #[arg(long, default_value_t = 1.0)]
    pub speed: f64,
    /// Where to serve (port 0: any free port; the address is printed as JSON).
    #[arg(long, default_value = "127.0.0.1:8765")]
    pub listen: std::net::SocketAddr,
    /// Start again from the beginning at the end, until stopped.
    #[arg(long = "loop")]
    pub loop_: bool,
}

#[derive(Args, Debug)]
pub struct EventsArgs {
    /// Stop by itself after this long (default: run until Ctrl-C).
    #[arg(long, value_parser = duration)]
    pub duration: Option<Duration>,
}

#[derive(Args, Debug)]
pub struct NetnsArgs {
    /// The hosts (comma-separated).
    #[arg(long, value_delimiter = ',', default_value = "a,b,c")]
    pub hosts: Vec<String>,
    /// The link between each pair of hosts.
    #[command(flatten)]
    pub link: LinkArgs,
    /// Print one JSON object (hosts, namespaces, addresses, proxies) instead of text.
    #[arg(long)]
    pub json: bool,
    /// Stop by itself after this long (default: run until Ctrl-C).
    #[arg(long, value_parser = duration)]
    pub duration: Option<Duration>,
}

#[derive(Args, Debug)]
pub struct NetProxyArgs {
    /// Where to listen.
    #[arg(long)]
    pub listen: std::net::SocketAddr,
    /// Where to connect each accepted connection to.
    #[arg(long)]
    pub to: std::net::SocketAddr,
    /// The link.
    #[command(flatten)]
    pub link: LinkArgs,
}

#[derive(Args, Debug)]
pub struct CertsArgs {
    /// Where the files go: ca.pem and ca.key (the authority, made if missing), and
    /// HOST.pem and HOST.key per host.
    #[arg(long, default_value = "muster-certs")]
    pub out: std::path::PathBuf,
    /// The hosts, as named by `muster broker --host` (comma-separated).
    #[arg(long, value_delimiter = ',', required = true)]
    pub hosts: Vec<String>,
    /// Further names and addresses each host's certificate is valid for (DNS names or
    /// IPs; localhost and 127.0.0.1 are always in).
    #[arg(long, value_delimiter = ',')]
    pub san: Vec<String>,
    /// Validity of the host certificates, days.
    #[arg(long, default_value_t = 825)]
    pub days: i64,
}

#[derive(Args, Debug)]
pub struct Ros2BenchArgs {
    /// A Python with rclpy (ROS 2 Kilted's wheels; see the README's "ROS 2").
    #[arg(long, default_value = ".venv/bin/python")]
    pub python: String,
    /// ROS domain id of the bridge rows (the simulator's is the next).
    #[arg(long, default_value_t = 90, value_parser = clap::value_parser!(u16).range(0..=231))]
    pub domain: u16,
    /// Samples timed one way (rclpy to muster, and rclpy to rclpy).
    #[arg(long, default_value_t = 1000)]
    pub samples: usize,
    /// Their rate, Hz.
    #[arg(long, default_value_t = 100.0)]
    pub rate: f64,
    /// Goals timed from a muster user to rclpy.
    #[arg(long, default_value_t = 200)]
    pub goals: usize,
    /// Simulator sizes (robots), each run with one rclpy node on every scan (none: skip).
    #[arg(long, value_delimiter = ',', default_value = "10,50,100")]
    pub robots: Vec<usize>,
    /// How long each simulator size is measured, once every scan flows.
    #[arg(long, default_value = "10s", value_parser = duration)]
    pub window: Duration,
    /// Print one JSON object instead of tables.
    #[arg(long)]
    pub json: bool,
}

#[derive(Args, Debug)]
pub struct WebBenchArgs {
    /// A Python with the `websockets` package (`bash scripts/test` makes `.venv`).
    #[arg(long, default_value = ".venv/bin/python")]
    pub python: String,
    /// WebSocket clients, each a user of its own.
    #[arg(long, default_value_t = 500)]
    pub clients: usize,
    /// Client processes they are spread over.
    #[arg(long, default_value_t = 2)]
    pub procs: usize,
    /// How long updates are timed once every client holds its session.
    #[arg(long, default_value = "30s", value_parser = duration)]
    pub duration: Duration,
    /// Requests timed at the broker before, and again while, the clients watch.
    #[arg(long, default_value_t = 200)]
    pub probes: usize,
    /// Print one JSON object instead of tables.
    #[arg(long)]
    pub json: bool,
}

#[derive(Args, Debug)]
pub struct Vda5050BenchArgs {
    /// Virtual vehicles, and muster users holding one each.
    #[arg(long, default_value_t = 100)]
    pub vehicles: usize,
    /// How long goals are given and timed once every user holds its vehicle.
    #[arg(long, default_value = "30s", value_parser = duration)]
    pub duration: Duration,
    /// Each user's time between goals.
    #[arg(long, default_value = "3s", value_parser = duration)]
    pub goal_every: Duration,
    /// Raw MQTT round trips timed (spread over the window).
    #[arg(long, default_value_t = 300)]
    pub round_trips: usize,
    /// The mosquitto program (Debian: /usr/sbin/mosquitto).
    #[arg(long, default_value = "mosquitto")]
    pub mosquitto: String,
    /// The folder of the VDA 5050 peers (`npm ci` done: `bash scripts/test` does it).
    #[arg(long, default_value = "bridges/vda5050/tests/js")]
    pub peers: std::path::PathBuf,
    /// Print one JSON object instead of tables.
    #[arg(long)]
    pub json: bool,
}

#[derive(Args, Debug)]
pub struct ListBenchArgs {
    /// Services listed.
    #[arg(long, default_value_t = 10_000)]
    pub services: usize,
    /// Services per page.
    #[arg(long, default_value_t = 100)]
    pub page: usize,
    /// Reads timed per row.
    #[arg(long, default_value_t = 20_000)]
    pub reads: usize,
    /// Seed of the pages' offsets.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Print one JSON object instead of a table.
    #[arg(long)]
    pub json: bool,
}

#[derive(Args, Debug)]
pub struct FederationBenchArgs {
    /// Service requests per row.
    #[arg(long, default_value_t = 500)]
    pub requests: usize,
    /// Raw Zenoh round trips (the floor).
    #[arg(long, default_value_t = 2000)]
    pub round_trips: usize,
    /// List changes timed between hosts.
    #[arg(long, default_value_t = 100)]
    pub list_changes: usize,
    /// How long session updates (10 Hz) are timed, per row (16 sessions a row, held
    /// at once: under load one session's latency is mostly its random turn in its
    /// system's fan-out).
    #[arg(long, default_value = "10s", value_parser = duration)]
    pub updates_for: Duration,
    /// Users per host (one process each) holding a session on another host for the
    /// loaded rows (0: no loaded rows).
    #[arg(long, default_value_t = 300)]
    pub users: usize,
    /// In the loaded rows, host b's users hold `t1/s0` on their own host instead of a
    /// session on c: the local update row is then one of as many subscribers of one
    /// host, on the same service's ticks, as the cross-host row's (whose host a fans
    /// each tick out to its users), like with like. Off: the local row's user is t1's
    /// only local subscriber.
    #[arg(long)]
    pub local_fan_out: bool,
    /// Times host b is lost (its broker SIGKILLed, then, as many times, SIGSTOPped:
    /// silent, its connections open) and comes back: until b's services leave a's list
    /// and until they are back.
    #[arg(long, default_value_t = 5)]
    pub losses: usize,
    /// The brokers' Zenoh lease (`muster broker --lease`): a silent host is gone after
    /// it (three hosts: 500 ms unless given; `--hosts`: Zenoh's default, 10 s).
    #[arg(long, value_parser = duration)]
    pub lease: Option<Duration>,
    /// Many hosts instead of three: N light hosts (a broker and a system of
    /// `--services-per-host` services each), every list read in place: the first start,
    /// the join of the Nth host, idle CPU, memory and loopback traffic, list changes
    /// until every host has them (`--list-changes`), host losses (`--losses`), and a
    /// restart of every broker at once.
    #[arg(long)]
    pub hosts: Option<usize>,
    /// With `--hosts`: how many hosts' brokers are Zenoh routers, the others their
    /// clients (0: every host a peer, as `muster up --hosts` runs them).
    #[arg(long, default_value_t = 0)]
    pub routers: usize,
    /// With `--hosts`: write each broker's log (its standard error) to
    /// `DIR/broker-HOST.log` (set `RUST_LOG` for more than warnings).
    #[arg(long)]
    pub logs: Option<std::path::PathBuf>,
    /// With `--hosts`: services of each host's system.
    #[arg(long, default_value_t = 100)]
    pub services_per_host: usize,
    /// With `--hosts`: how long idle CPU and traffic are measured.
    #[arg(long, default_value = "10s", value_parser = duration)]
    pub idle: Duration,
    /// Print one JSON object instead of a table.
    #[arg(long)]
    pub json: bool,
}

#[derive(Args, Debug)]
pub struct FailoverArgs {
    /// Takeovers to cause.
    #[arg(long, default_value_t = 100)]
    pub kills: usize,
    /// Users holding a data session through the whole run (one process each).
    #[arg(long, default_value_t = 200)]
    pub users: usize,
    /// Users making requests one after another (one process each).
    #[arg(long, default_value_t = 20)]
    pub requesters: usize,
    /// Systems (synthetic, 10 Hz data services).
    #[arg(long, default_value_t = 20)]
    pub systems: usize,
    /// Services per system.
    #[arg(long, default_value_t = 4)]
    pub services_per_system: usize,
    /// How the primary fails: kill (SIGKILL), stop (SIGSTOP), hang (its loop stops while
    /// the process lives: every broker runs with `--fault hang-on-usr1`, and SIGUSR1
    /// hangs it), both (kill and stop, alternating) or all three in turn.
    #[arg(long, default_value = "both")]
    pub signal: String,
    /// The standbys' --takeover-deadline.
    #[arg(long, default_value = "100ms", value_parser = duration)]
    pub deadline: Duration,
    /// A requester's pause between two requests.
    #[arg(long, default_value = "20ms", value_parser = duration)]
    pub pause: Duration,
    /// How long the load runs between two rounds.
    #[arg(long, default_value = "500ms", value_parser = duration)]
    pub settle: Duration,
    /// Print one JSON object instead of a table.
    #[arg(long)]
    pub json: bool,
}

#[derive(Args, Debug)]
pub struct LeftoversArgs {
    /// SIGKILLs per kind.
    #[arg(long, default_value_t = 100)]
    pub kills: usize,
    /// The kinds (comma-separated).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "broker,standby,system,user,sim,federated"
    )]
    pub kinds: Vec<String>,
    /// Print one JSON object instead of a table.
    #[arg(long)]
    pub json: bool,
}

#[derive(Args, Debug)]
pub struct FailoverUserArgs {
    /// Hold a session of this service until SIGTERM.
    #[arg(long)]
    pub hold: Option<String>,
    /// Request these services (comma-separated) in turn, ending each session at once.
    #[arg(long)]
    pub request: Option<String>,
    /// Pause between two requests.
    #[arg(long, default_value = "20ms", value_parser = duration)]
    pub pause: Duration,
    #[command(flatten)]
    pub remote: RemoteArgs,
}

#[derive(Args, Debug)]
pub struct FloorArgs {
    /// Round trips to time.
    #[arg(long, default_value_t = 2000)]
    pub round_trips: usize,
    /// Print one JSON object instead of a table.
    #[arg(long)]
    pub json: bool,
}

#[derive(Args, Debug)]
pub struct LivenessArgs {
    /// Repetitions of each measurement.
    #[arg(long, default_value_t = 10)]
    pub trials: usize,
    /// Systems (8 services each) registered during the broker-restart trials.
    #[arg(long, default_value_t = 10)]
    pub systems: usize,
    /// Users holding a data session (one process each) during the broker-restart trials.
    #[arg(long, default_value_t = 0)]
    pub users: usize,
    /// Kill each restarted broker as soon as its list is complete, without waiting for
    /// the cleanup after the one before (dead brokers pile up: a crash loop).
    #[arg(long)]
    pub crash_loop: bool,
    /// Print one JSON object instead of a table.
    #[arg(long)]
    pub json: bool,
}

#[derive(Args, Debug)]
pub struct ScaleArgs {
    #[command(flatten)]
    pub load: LoadArgs,
    /// How long to measure the broker's CPU with every user connected and idle.
    #[arg(long, default_value = "10s", value_parser = duration)]
    pub idle: Duration,
    /// Request round trips to time with every user connected.
    #[arg(long, default_value_t = 500)]
    pub requests: usize,
    /// Print one JSON object instead of a table.
    #[arg(long)]
    pub json: bool,
}

fn fault(s: &str) -> Result<muster_broker::run::Fault, String> {
    match s.split_once(':') {
        Some(("hang-after", n)) => n
            .parse()
            .map(muster_broker::run::Fault::HangAfter)
            .map_err(|e| format!("hang-after:N takes a number of passes ({e})")),
        None if s == "hang-on-usr1" => Ok(muster_broker::run::Fault::HangOnUsr1),
        _ => Err(format!("unknown fault {s:?} (hang-after:N, hang-on-usr1)")),
    }
}

fn duration(s: &str) -> Result<Duration, String> {
    humantime::parse_duration(s).map_err(|e| format!("{e} (examples: 500ms, 5s, 2m)"))
}

#[derive(Args, Debug)]
pub struct BrokerArgs {
    /// On stopping, write every message's handling time to this CSV (`at_ms,kind,us`:
    /// CLOCK_MONOTONIC ms, message kind or `list_write`, µs), for plots over a run.
    #[arg(long)]
    pub handling_log: Option<std::path::PathBuf>,
    /// How often each system is pinged (scenario time: see `--time-scale`).
    #[arg(long, default_value = "20s", value_parser = duration)]
    pub ping_interval: Duration,
    /// How long a system has to answer a ping before it is delinquent (scenario time,
    /// never under 500 ms of wall time).
    #[arg(long, default_value = "10s", value_parser = duration)]
    pub ping_timeout: Duration,
    /// How long a system has to answer a forwarded request.
    #[arg(long, default_value = "10s", value_parser = duration)]
    pub offer_timeout: Duration,
    /// Most requests one service's task queue holds.
    #[arg(long, default_value_t = 32)]
    pub queue_capacity: u16,
    /// Most links one user may have counted in the list.
    #[arg(long, default_value_t = muster_broker::core::MAX_LINKS_PER_USER)]
    pub max_links_per_user: usize,
    /// Most users one local process may hold at once. `muster web` is one user per
    /// person signed in: give its broker at least as many as sign in at once.
    #[arg(long, default_value_t = muster_broker::core::MAX_USERS_PER_PROCESS)]
    pub max_users_per_process: usize,
    /// Most services listed at once: a system that would take the list past it is
    /// refused. The list itself has no fixed size (it grows in shared memory and is
    /// paged to remote users); this keeps a runaway system from filling memory.
    #[arg(long, default_value_t = muster_shared::snapshot::DEFAULT_MAX_SERVICES)]
    pub max_services: usize,
    /// On stopping, print one JSON line: counters and time to handle each message type.
    #[arg(long)]
    pub stats_json: bool,
    /// Also serve remote users on this UDP address (e.g. `127.0.0.1:7400`).
    #[arg(long)]
    pub udp: Option<std::net::SocketAddr>,
    /// The broker's key file (from `muster keygen --broker`); default: a fresh key each
    /// start, its public half logged.
    #[arg(long, requires = "udp")]
    pub key: Option<std::path::PathBuf>,
    /// Access file: which remote users (name, public key) may list and request which
    /// services. Re-read on SIGHUP. Without it every remote user is refused.
    #[arg(long, requires = "udp")]
    pub access: Option<std::path::PathBuf>,
    /// Datagrams per second one remote user may send (bursts of twice that); more are
    /// dropped and counted.
    #[arg(long, default_value_t = 2000.0, requires = "udp")]
    pub udp_conn_rate: f64,
    /// Most remote users connected at once (a connection costs the broker a few KiB);
    /// the next handshake is refused until one leaves.
    #[arg(long, default_value_t = muster_broker::udp::DEFAULT_MAX_REMOTE_USERS, requires = "udp")]
    pub udp_max_users: usize,
    /// Run as a standby: follow the running broker's state and take over when it dies,
    /// hangs past --takeover-deadline or steps down. Any number may run.
    #[arg(long)]
    pub standby: bool,
    /// How long a standby waits without a word from the primary before it judges it:
    /// taken over if stopped, or if its loop made no progress while it could have run;
    /// left alone if it is only starved of a core (wall time).
    #[arg(long, default_value = "100ms", value_parser = duration, requires = "standby")]
    pub takeover_deadline: Duration,
    /// A deliberate fault, for tests and benches: `hang-after:N` stops the primary's
    /// loop after N passes while its process lives on (as a deadlock would).
    #[arg(long, hide = true, value_parser = fault)]
    pub fault: Option<muster_broker::run::Fault>,
    /// Join a federation of hosts over Zenoh: publish this host's services, see every
    /// host's, and serve requests across hosts.
    #[arg(long)]
    pub federate: bool,
    /// This host's name in the federation (default: the machine's host name).
    #[arg(long, requires = "federate")]
    pub host: Option<String>,
    /// The federation's name: federations with different names share a network unseen.
    #[arg(long, default_value = "muster", requires = "federate")]
    pub federation: String,
    /// A Zenoh configuration file (JSON5), e.g. for TLS; --connect, --listen and
    /// --lease apply over it.
    #[arg(long, requires = "federate")]
    pub zenoh_config: Option<std::path::PathBuf>,
    /// Connect to this Zenoh endpoint (e.g. `tcp/10.0.0.2:7447`); repeatable.
    #[arg(long, requires = "federate")]
    pub connect: Vec<String>,
    /// Listen on this Zenoh endpoint (e.g. `tcp/0.0.0.0:7447`); repeatable. Default:
    /// loopback only (`tcp/127.0.0.1:0`).
    #[arg(long, requires = "federate")]
    pub listen: Vec<String>,
    /// A host silent this long is gone, its services removed from the others' lists
    /// (Zenoh's lease; its default is 10 s).
    #[arg(long, value_parser = duration, requires = "federate")]
    pub lease: Option<Duration>,
    /// Find other hosts on the LAN by Zenoh's multicast scouting (off by default:
    /// name them with --connect).
    #[arg(long, requires = "federate")]
    pub multicast: bool,
    /// How this broker joins Zenoh: `peer` (default: a link to every other host), or,
    /// for many hosts, `router` on a few (meshed among themselves) and `client` on the
    /// rest (one link to a router; --connect every router, no --listen).
    #[arg(long, requires = "federate")]
    pub zenoh_mode: Option<muster_broker::federation::ZenohMode>,
    /// Mutual TLS with the certificates in DIR (from `muster certs`): ca.pem, HOST.pem,
    /// HOST.key. Endpoints given as tcp/ are used as tls/; a host whose certificate the
    /// authority did not sign joins nothing.
    #[arg(long, requires = "federate")]
    pub tls: Option<std::path::PathBuf>,
    /// The federation's access file (TOML, the same on every host): `[hosts]` then
    /// `NAME = ["offer", "request"]` per host. Hosts not named, or acting beyond their
    /// roles, are let do nothing. Needs --tls; default `acl.toml` in the --tls folder
    /// (`muster certs` writes it).
    #[arg(long, requires = "tls")]
    pub acl: Option<std::path::PathBuf>,
    /// Federate without TLS: no authentication, anyone reaching the endpoint can act as
    /// any host. Refused without this flag; warned of at every start.
    #[arg(long, requires = "federate", conflicts_with = "tls")]
    pub insecure_no_tls: bool,
}

#[derive(Subcommand, Debug)]
pub enum SystemCommand {
    /// A generic system offering K services (streaming poses, or driving to goals).
    Synthetic(SyntheticArgs),
    /// The paper's tracking system on the simulator: robots with PTZ cameras track
    /// coloured beacons; one data service (`track2d`) per colour.
    Tracking(TrackingArgs),
    /// The paper's delivery robot on the simulator: one command service (`goal2d`) with
    /// a task queue; plans, drives, avoids, reports, goes home when idle.
    Delivery(DeliveryArgs),
    /// A ROS 2 robot as a muster system, with no code: its topics become services as the
    /// config file says (see the README's "ROS 2").
    Ros2(Ros2SystemArgs),
    /// A VDA 5050 fleet's vehicles as muster services (over MQTT): per vehicle, a
    /// command service (a goal becomes an order) and a data service (its state).
    Vda5050(Vda5050SystemArgs),
}

/// How to reach an MQTT broker that asks for TLS or a password.
#[derive(Args, Debug, Clone)]
pub struct MqttArgs {
    /// TLS to the MQTT broker, trusting the certificate authorities in this PEM file
    /// (the broker's certificate must name the host or address of `--mqtt`).
    #[arg(long)]
    pub mqtt_ca: Option<std::path::PathBuf>,
    /// With `--mqtt-ca`: this client's certificate chain and its key (PEM), for a broker
    /// that asks for one.
    #[arg(long, num_args = 2, value_names = ["CERT", "KEY"], requires = "mqtt_ca")]
    pub mqtt_client_cert: Option<Vec<std::path::PathBuf>>,
    /// The MQTT user name (its password from `--mqtt-password-file`).
    #[arg(long, requires = "mqtt_password_file")]
    pub mqtt_user: Option<String>,
    /// A file whose first line is the MQTT password (never on the command line).
    #[arg(long, requires = "mqtt_user")]
    pub mqtt_password_file: Option<std::path::PathBuf>,
    /// A folder of VDA 5050 JSON schemas (the official ones of the version spoken:
    /// `order.schema`, `state.schema.json`, ...): every message read and written must
    /// also pass them (checked with `jsonschema`).
    #[arg(long)]
    pub vda_schemas: Option<std::path::PathBuf>,
}

#[derive(Args, Debug)]
pub struct AgvArgs {
    /// The MQTT broker, HOST:PORT.
    #[arg(long)]
    pub mqtt: String,
    #[command(flatten)]
    pub mqtt_security: MqttArgs,
    /// The robots (each one vehicle, its serial number the robot's name).
    #[arg(long, value_delimiter = ',', default_value = "D1")]
    pub robots: Vec<String>,
    /// `interfaceName` of the topics.
    #[arg(long, default_value = "uagv")]
    pub interface: String,
    /// The vehicles' manufacturer.
    #[arg(long, default_value = "muster")]
    pub manufacturer: String,
    /// The VDA 5050 version written (2.x.y; vda-5050-lib speaks 2.0.0).
    #[arg(long, default_value = "2.1.0")]
    pub vda_version: String,
    /// The map id of the robots' positions (orders must use it).
    #[arg(long, default_value = "muster")]
    pub map_id: String,
    /// A node is reached within this distance, m (unless the order allows more); a new
    /// order's first node must be this close.
    #[arg(long, default_value_t = 0.5)]
    pub deviation: f64,
    /// State at least this often (VDA 5050: at most 30 s).
    #[arg(long, default_value = "30s", value_parser = duration)]
    pub state_every: Duration,
    /// Visualization this often (`0s`: none).
    #[arg(long, default_value = "1s", value_parser = duration)]
    pub visualization_every: Duration,
    #[command(flatten)]
    pub common: RobotSystemArgs,
}

#[derive(Args, Debug)]
pub struct Vda5050SystemArgs {
    /// The MQTT broker, HOST:PORT.
    #[arg(long)]
    pub mqtt: String,
    #[command(flatten)]
    pub mqtt_security: MqttArgs,
    /// `interfaceName` of the topics.
    #[arg(long, default_value = "uagv")]
    pub interface: String,
    /// Only this manufacturer's vehicles (default: all).
    #[arg(long)]
    pub manufacturer: Option<String>,
    /// The muster system's name.
    #[arg(long, default_value = "vda5050")]
    pub name: String,
    /// The VDA 5050 version written to a vehicle before it said its own (2.x.y).
    #[arg(long, default_value = "2.1.0")]
    pub vda_version: String,
    /// The road map (JSON: mapId, nodes with id/x/y, edges): goals go to its nearest
    /// node along the shortest path. Without it, orders go straight to the point.
    #[arg(long)]
    pub graph: Option<std::path::PathBuf>,
    /// How long a vehicle has to show an order in its state.
    #[arg(long, default_value = "10s", value_parser = duration)]
    pub order_timeout: Duration,
    /// How long to wait at start for the vehicles the MQTT broker knows.
    #[arg(long, default_value = "2s", value_parser = duration)]
    pub wait: Duration,
    /// Serve remote users' sessions on this UDP address (e.g. `127.0.0.1:0`).
    #[arg(long)]
    pub udp: Option<std::net::SocketAddr>,
    /// Print the bridge's counters as JSON when it stops.
    #[arg(long)]
    pub stats_json: bool,
}

#[derive(Args, Debug)]
pub struct Ros2SystemArgs {
    /// The config: the system's name, its data and command services and their topics.
    #[arg(long)]
    pub config: std::path::PathBuf,
    /// ROS domain id (default: `ROS_DOMAIN_ID`, else 0).
    #[arg(long, value_parser = clap::value_parser!(u16).range(0..=232))]
    pub domain: Option<u16>,
    /// Twist services: zero velocity when a session's input stops this long (a service's
    /// own `deadman` in the file wins).
    #[arg(long, default_value = "0.5s", value_parser = duration)]
    pub deadman: Duration,
    /// Serve remote users' sessions on this UDP address (e.g. `127.0.0.1:0`).
    #[arg(long)]
    pub udp: Option<std::net::SocketAddr>,
}

/// What every robot system on the simulator takes.
#[derive(Args, Debug, Clone)]
pub struct RobotSystemArgs {
    /// The simulator's scenario (TOML; default: the paper's). Must match `muster sim`'s.
    /// With `--ros2` the robots describe themselves instead (see `--robot-params`).
    #[arg(long, conflicts_with = "ros2")]
    pub scenario: Option<std::path::PathBuf>,
    /// Map (map_server YAML; default: the scenario's, or the built-in office; with
    /// `--ros2`, the one on `/map`).
    #[arg(long)]
    pub map: Option<std::path::PathBuf>,
    /// Use the simulator's ground-truth poses instead of localizing (experiments only).
    #[arg(long)]
    pub ground_truth: bool,
    /// How long to wait for the simulator to come up (with `--ros2`: for each robot's
    /// first scan, odometry and map).
    #[arg(long, default_value = "20s", value_parser = duration)]
    pub wait_sim: Duration,
    /// Seed of the filters' randomness.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// On stopping, print one JSON line: grants and refusals per service, localization
    /// error against ground truth per robot.
    #[arg(long)]
    pub stats_json: bool,
    /// Serve remote users' sessions on this UDP address (e.g. `127.0.0.1:0`).
    #[arg(long)]
    pub udp: Option<std::net::SocketAddr>,
    /// Drive the robots through ROS 2 topics in each robot's namespace (`/ROBOT/scan`,
    /// `odom`, `sonar`, `beacons`, `ptz`, `cmd_vel`, `ptz_cmd`) instead of the
    /// simulator's shared memory: any ROS 2 robot, the simulator bridged by `muster sim
    /// --ros2` among them.
    #[arg(long)]
    pub ros2: bool,
    /// With `--ros2`: the ROS domain id (default: `ROS_DOMAIN_ID`, else 0).
    #[arg(long, requires = "ros2", value_parser = clap::value_parser!(u16).range(0..=232))]
    pub domain: Option<u16>,
    /// With `--ros2`: what the robots' topics do not say (TOML, a table per robot:
    /// `radius`, `max_speed`, `start = [x, y, heading_deg]`, `home = [x, y]`, `camera`);
    /// the laser comes from the first scan, the sonar from `/tf_static`, the map from
    /// `/map` or `--map`.
    #[arg(long, requires = "ros2")]
    pub robot_params: Option<std::path::PathBuf>,
}

#[derive(Args, Debug)]
pub struct TrackingArgs {
    /// System name.
    #[arg(long, default_value = "tracking")]
    pub name: String,
    /// Robots it drives (default: every robot of the scenario with a camera).
    #[arg(long, value_delimiter = ',')]
    pub robots: Vec<String>,
    /// Robots among them that may drive: they patrol while their target is lost and
    /// follow it when seen (Experiment 2: T3). Default: all stationary.
    #[arg(long, value_delimiter = ',')]
    pub mobile: Vec<String>,
    /// Beacon colours, one service each.
    #[arg(long, value_delimiter = ',', default_value = "red,green,blue")]
    pub colours: Vec<String>,
    /// Sessions each colour's service accepts at once.
    #[arg(long, default_value_t = 10)]
    pub quota: u16,
    /// Updates per second (sim time; the paper: 1).
    #[arg(long, default_value_t = 1.0)]
    pub rate: f64,
    /// A target unseen this long (sim seconds) is reported lost.
    #[arg(long, default_value_t = 5.0)]
    pub lost_after: f64,
    /// Do not model the robots' processing budget (sessions limited by quota only).
    #[arg(long)]
    pub no_budget: bool,
    /// The colour mobile trackers follow (default: the most requested one that is
    /// tracked).
    #[arg(long)]
    pub follow: Option<String>,
    /// Where mobile trackers patrol while their target is lost: waypoints `X,Y`
    /// separated by spaces (default: the office's corridor loop).
    #[arg(long, value_delimiter = ' ')]
    pub patrol: Vec<String>,
    #[command(flatten)]
    pub common: RobotSystemArgs,
}

#[derive(Args, Debug)]
pub struct DeliveryArgs {
    /// System name.
    #[arg(long, default_value = "delivery")]
    pub name: String,
    /// The robot it drives.
    #[arg(long, default_value = "D1")]
    pub robot: String,
    /// The command service's name (default: the robot's).
    #[arg(long)]
    pub service: Option<String>,
    /// Sessions at once (the paper: one user tasks the robot at a time).
    #[arg(long, default_value_t = 1)]
    pub quota: u16,
    /// Refuse requests beyond the quota instead of queueing them.
    #[arg(long)]
    pub no_queue: bool,
    /// Not tasked for this long (sim seconds), it returns home.
    #[arg(long, default_value_t = 60.0)]
    pub home_after: f64,
    /// With `--ros2`: the robot's namespace (default `/ROBOT`).
    #[arg(long, requires = "ros2")]
    pub namespace: Option<String>,
    #[command(flatten)]
    pub common: RobotSystemArgs,
}

#[derive(Args, Debug)]
pub struct SyntheticArgs {
    /// System name, unique on the instance.
    #[arg(long)]
    pub name: String,
    /// How many services to offer.
    #[arg(long, default_value_t = 1)]
    pub services: usize,
    /// Service kind: data or command.
    #[arg(long, default_value = "data")]
    pub kind: ServiceKind,
    /// Sessions each service accepts at once.
    #[arg(long, default_value_t = 10)]
    pub quota: u16,
    /// Keep a task queue: requests beyond the quota wait instead of being refused.
    #[arg(long)]
    pub queue: bool,
    /// Payload type name (default pose2d for data, goal2d for command).
    #[arg(long)]
    pub payload: Option<String>,
    /// Update rate, Hz of scenario time (see `--time-scale`).
    #[arg(long, default_value_t = 10.0)]
    pub rate: f64,
    /// Latch the data services (ROS 2's transient-local durability): they update at
    /// their rate even with no session, the broker keeps each one's newest value, and a
    /// new session gets it with its grant, as its update 0.
    #[arg(long)]
    pub latched: bool,
    /// On stopping, print one JSON line per service: quota, most sessions at once,
    /// grants and refusals.
    #[arg(long)]
    pub stats_json: bool,
    /// Serve remote users' sessions on this UDP address (e.g. `127.0.0.1:0`).
    #[arg(long)]
    pub udp: Option<std::net::SocketAddr>,
}

#[derive(Args, Debug)]
pub struct UserArgs {
    /// How long to wait for a broker.
    #[arg(long, default_value = "5s", value_parser = duration, global = true)]
    pub wait: Duration,
    #[command(flatten)]
    pub remote: RemoteArgs,
    /// Without a verb: the plain numbered menu even on a terminal (it is the one used
    /// when standard input or output is not a terminal, or TERM is dumb).
    #[arg(long)]
    pub plain: bool,
    /// `idle` and `behave` only: run this many users in this process, each its own
    /// connection (its own UDP socket and key exchange with `--remote`) on its own
    /// thread, each printing its own line (`behave`: seeds SEED, SEED+1, ...). A
    /// harness's way to many users without a process each; local users are capped per
    /// process by the broker (16 unless it says more).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=1000))]
    pub count: u32,
    /// With `--count`, local users: give each user an inbox of its own instead of one
    /// the process's users share (the default: the broker and the systems then hold
    /// one pair of ports, about ten descriptors, for the process, not one per user).
    #[arg(long)]
    pub own_inboxes: bool,
    /// Without a verb: the menu shows this part of the list.
    #[command(flatten)]
    pub list: ListFilterArgs,
    #[command(subcommand)]
    pub verb: Option<UserVerb>,
}

/// Which part of the service list to show.
#[derive(Args, Debug, Clone, Default)]
pub struct ListFilterArgs {
    /// Only services offered by this host (in a federation).
    #[arg(long)]
    pub host: Option<String>,
    /// Only services of this system.
    #[arg(long)]
    pub system: Option<String>,
    /// Only `data` or only `command` services.
    #[arg(long, value_parser = ["data", "command"])]
    pub kind: Option<String>,
    /// Only services of this payload type (e.g. `goal2d`, `geometry_msgs/msg/Twist`).
    #[arg(long)]
    pub payload: Option<String>,
    /// Only services whose name matches this glob (`*`, `?`, `[..]`, `{a,b}`).
    #[arg(long)]
    pub name: Option<String>,
    /// Skip this many of the services let through.
    #[arg(long, default_value_t = 0)]
    pub offset: usize,
    /// Show at most this many.
    #[arg(long)]
    pub limit: Option<usize>,
}

impl ListFilterArgs {
    /// The part of the list these flags name.
    pub fn part(&self) -> muster_shared::snapshot::ListPart {
        muster_shared::snapshot::ListPart {
            filter: self.filter(),
            offset: self.offset,
            limit: self.limit.unwrap_or(usize::MAX),
        }
    }

    /// The filter these flags name.
    pub fn filter(&self) -> muster_shared::snapshot::ListFilter {
        use muster_shared::types::ServiceKind;
        muster_shared::snapshot::ListFilter {
            host: self.host.clone(),
            system: self.system.clone(),
            kind: self.kind.as_deref().map(|k| {
                if k == "command" {
                    ServiceKind::Command
                } else {
                    ServiceKind::Data
                }
            }),
            payload: self.payload.clone(),
            name: self.name.clone(),
        }
    }
}

#[derive(Subcommand, Debug)]
pub enum UserVerb {
    /// Print the service list snapshot, or the part of it the filters let through, a
    /// page at a time with `--offset` and `--limit`.
    List {
        #[command(flatten)]
        filter: ListFilterArgs,
        /// One JSON array instead of a table.
        #[arg(long)]
        json: bool,
    },
    /// Request a service and print the answer and then each update until the duration ends.
    Request {
        /// Service id, `system/service` (see `muster user list`).
        id: String,
        /// How long to keep the session.
        #[arg(long, default_value = "5s", value_parser = duration)]
        duration: Duration,
        /// For a command service: send this goal once granted, `X,Y` in metres.
        #[arg(long, allow_hyphen_values = true, conflicts_with = "twist")]
        goal: Option<String>,
        /// For a command service taking `twist`: drive at `V,W` (m/s, rad/s), sent 10
        /// times a second while the session lasts, as a joystick does (the robot stops
        /// when it stops coming).
        #[arg(long, allow_hyphen_values = true)]
        twist: Option<String>,
        /// For a command service: send this input once granted, as JSON: a string
        /// (text), a number (scalar), `{"type": "goal2d", "x": 1, "y": 2}` (or pose2d,
        /// twist, text, scalar), or an open type's `{"type": "pkg/msg/T", "value": {..}}`
        /// written with the service's schema.
        #[arg(long, allow_hyphen_values = true, conflicts_with_all = ["goal", "twist"])]
        input: Option<String>,
        /// One JSON object a line.
        #[arg(long)]
        json: bool,
    },
    /// Stay connected, idle, and print the list each time it changes (with filters:
    /// the part they let through, each time that part changes).
    Watch {
        #[command(flatten)]
        filter: ListFilterArgs,
        /// Stop after this long (default: until Ctrl-C).
        #[arg(long, value_parser = duration)]
        duration: Option<Duration>,
        /// One JSON object a line: `{"generation": .., "services": [..]}`.
        #[arg(long)]
        json: bool,
    },
    /// Connect, print one JSON line `{"connected": true, "services": N}`, and stay idle
    /// (not notified of list changes) until the duration ends or a signal: an idle user.
    Idle {
        /// Stop after this long (default: until Ctrl-C).
        #[arg(long, value_parser = duration)]
        duration: Option<Duration>,
    },
    /// Behave like one of the paper's users for a while (list, refresh, request, hold
    /// sessions, end them, sometimes link), then print one JSON line of counts and
    /// latency samples. The stress harness runs hundreds of these.
    Behave(BehaveArgs),
    /// Link a data service into a command service: data becomes the command's task input.
    Link {
        /// Data service id.
        data: String,
        /// Command service id.
        command: String,
        /// How long to keep the link.
        #[arg(long, default_value = "5s", value_parser = duration)]
        duration: Duration,
        /// One JSON object a line.
        #[arg(long)]
        json: bool,
    },
}

#[derive(Args, Debug)]
pub struct UpArgs {
    /// Stop by itself after this long (default: run until Ctrl-C).
    #[arg(long, value_parser = duration)]
    pub duration: Option<Duration>,
    /// Where the broker serves remote users (port 0: any free port).
    #[arg(long, default_value = "127.0.0.1:7400")]
    pub udp: std::net::SocketAddr,
    /// Serve local users only.
    #[arg(long)]
    pub no_udp: bool,
    /// Run no standby broker (by default one follows the broker and takes over if it
    /// dies or hangs; the run says when).
    #[arg(long)]
    pub no_standby: bool,
    /// Today's synthetic demo instead of the paper's robots on the simulator.
    #[arg(long)]
    pub synthetic: bool,
    /// Three hosts federated over Zenoh on this machine (three instances on loopback):
    /// the user on host a, a tracker on b, a delivery robot on c (synthetic systems).
    #[arg(long, conflicts_with_all = ["synthetic", "speed", "picture"])]
    pub hosts: bool,
    /// With `--hosts`: each host in a network namespace of its own, joined to the others
    /// through a proxy per pair of hosts that adds `--delay` and `--loss` (needs root;
    /// `muster netns` makes the same network).
    #[arg(long, requires = "hosts")]
    pub netns: bool,
    /// The link between each pair of hosts, with `--netns`.
    #[command(flatten)]
    pub link: LinkArgs,
    /// Simulator speed (sim seconds per wall second; every process follows its clock).
    #[arg(long, default_value_t = 1.0)]
    pub speed: f64,
    /// Where the web console listens (`muster web`; another free port if taken).
    #[arg(long, default_value = "127.0.0.1:8080")]
    pub web: std::net::SocketAddr,
    /// Start no web console.
    #[arg(long)]
    pub no_web: bool,
    /// Where to write the picture of the run (default: muster-up-INSTANCE.png in the
    /// temporary folder).
    #[arg(long)]
    pub picture: Option<std::path::PathBuf>,
}

#[derive(Args, Debug)]
pub struct SimArgs {
    /// Scenario file (TOML); default: the paper's three trackers, delivery robot, three people.
    #[arg(long)]
    pub scenario: Option<std::path::PathBuf>,
    /// Map (ROS map_server YAML), overriding the scenario's.
    #[arg(long)]
    pub map: Option<std::path::PathBuf>,
    /// Simulated seconds per wall-clock second (default: `--time-scale`).
    #[arg(long, conflicts_with = "as_fast_as_possible")]
    pub speed: Option<f64>,
    /// Run as fast as the machine allows.
    #[arg(long)]
    pub as_fast_as_possible: bool,
    /// Seed of every random draw (overrides the scenario's).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Stop after this much simulated time.
    #[arg(long, value_parser = duration)]
    pub duration: Option<Duration>,
    /// Draw the world into this PNG (after `--at` simulated seconds) and exit.
    #[arg(long)]
    pub render: Option<std::path::PathBuf>,
    /// Simulated seconds to run before `--render`.
    #[arg(long, default_value_t = 0.0, requires = "render")]
    pub at: f64,
    /// Print the real-time factor for 1, 10, 100, 1000 and 10000 wandering robots with all
    /// sensors on, and the time per laser beam; then exit.
    #[arg(long)]
    pub bench: bool,
    /// Robot counts for `--bench`.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "1,10,100,1000,10000",
        requires = "bench"
    )]
    pub robots: Vec<usize>,
    /// With `--bench`: one JSON object a line.
    #[arg(long, requires = "bench")]
    pub json: bool,
    /// Write the map (built-in office unless `--map`) as map_server YAML + PGM and exit.
    #[arg(long)]
    pub export_map: Option<std::path::PathBuf>,
    /// Also bridge every robot to ROS 2: `scan`, `sonar`, `odom`, `ground_truth` and
    /// `cmd_vel` in each robot's namespace, `/clock` (sim time), `/map`, `/people`,
    /// `/tf`, `/tf_static` (see the README's "ROS 2").
    #[arg(long)]
    pub ros2: bool,
    /// ROS domain id for `--ros2` (default: `ROS_DOMAIN_ID`, else 0).
    #[arg(long, requires = "ros2", value_parser = clap::value_parser!(u16).range(0..=232))]
    pub domain: Option<u16>,
    /// Also make the robots VDA 5050 vehicles on the MQTT broker HOST:PORT: runs `muster
    /// agv` beside the simulator (stopped with it) for `--vda5050-robots`, with this
    /// scenario and map.
    #[arg(long, value_name = "HOST:PORT")]
    pub vda5050: Option<String>,
    /// With `--vda5050`: which robots (default: every robot of the scenario).
    #[arg(long, value_delimiter = ',', requires = "vda5050")]
    pub vda5050_robots: Vec<String>,
}

#[derive(Args, Debug, Clone)]
pub struct BehaveArgs {
    /// How long to behave (scenario time, like every duration here: see `--time-scale`).
    #[arg(long, default_value = "30s", value_parser = duration)]
    pub duration: Duration,
    /// Wait for a line, or the end, on standard input before connecting: a harness
    /// starts hundreds of users at one moment (`muster stress --together`).
    #[arg(long)]
    pub start_on_stdin: bool,
    /// Seed of this user's choices.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Mean time between list refreshes.
    #[arg(long, default_value = "5s", value_parser = duration)]
    pub refresh: Duration,
    /// Mean pause between interactions.
    #[arg(long, default_value = "2s", value_parser = duration)]
    pub think: Duration,
    /// Shortest time a session is held.
    #[arg(long, default_value = "1s", value_parser = duration)]
    pub hold_min: Duration,
    /// Longest time a session is held.
    #[arg(long, default_value = "5s", value_parser = duration)]
    pub hold_max: Duration,
    /// Chance that an interaction is a link instead of a request.
    #[arg(long, default_value_t = 0.1)]
    pub link_prob: f64,
    /// Chance that a request takes several services of one system at once.
    #[arg(long, default_value_t = 0.0)]
    pub multi_prob: f64,
    /// Most services such a request takes beside the first (1 to this many, at random).
    #[arg(long, default_value_t = 1)]
    pub multi_extra: usize,
    /// Goals (x,y;x,y;...) sent into command sessions: one at the grant, then another
    /// every `--goal-every`.
    #[arg(long, value_parser = goals, default_value = "")]
    pub goals: Goals,
    /// Time between goals sent into a command session.
    #[arg(long, default_value = "60s", value_parser = duration)]
    pub goal_every: Duration,
}

/// Goal points for scripted users.
pub type Goals = Vec<(f64, f64)>;

fn goals(s: &str) -> Result<Goals, String> {
    s.split(';')
        .filter(|p| !p.trim().is_empty())
        .map(|p| {
            let (x, y) = p.split_once(',').ok_or(format!("{p:?} is not x,y"))?;
            let x: f64 = x
                .trim()
                .parse()
                .map_err(|_| format!("{x:?} is not a number"))?;
            let y: f64 = y
                .trim()
                .parse()
                .map_err(|_| format!("{y:?} is not a number"))?;
            if x.is_finite() && y.is_finite() {
                Ok((x, y))
            } else {
                Err(format!("{p:?} is not a finite point"))
            }
        })
        .collect()
}

#[derive(Args, Debug)]
pub struct StressArgs {
    /// Users, services, and systems (in `stress`, even systems offer data services and
    /// odd ones command services; every third keeps a task queue; quotas 1..10).
    #[command(flatten)]
    pub load: LoadArgs,
    /// How long the users behave.
    #[arg(long, default_value = "120s", value_parser = duration)]
    pub duration: Duration,
    /// The users' niceness. Default: their own, or, when the broker could not lower its
    /// own (no privileges), as much above it as the broker would have been below.
    #[arg(long, allow_hyphen_values = true, value_parser = clap::value_parser!(i32).range(-20..=19))]
    pub users_nice: Option<i32>,
    /// Mean pause between a user's interactions.
    #[arg(long, default_value = "2s", value_parser = duration)]
    pub think: Duration,
    /// Mean time between a user's list refreshes.
    #[arg(long, default_value = "5s", value_parser = duration)]
    pub refresh: Duration,
    /// Write report.json into this folder.
    #[arg(long)]
    pub report: Option<std::path::PathBuf>,
    /// Print the report as one JSON object instead of a table.
    #[arg(long)]
    pub json: bool,
    /// Users connect over UDP (authenticated, through the broker's front and the
    /// systems' endpoints); the floor is then also the raw UDP loopback round trip.
    #[arg(long)]
    pub remote: bool,
    /// Idle mode: the users connect and do nothing for `--duration`; reports the CPU of
    /// the broker, the systems and the users, and memory.
    #[arg(long)]
    pub idle: bool,
    /// Start every user at one moment: all user processes are started first and wait;
    /// then all are let go at once and connect together (a storm of arrivals, and later
    /// of departures). The run's seconds count from that moment.
    #[arg(long, conflicts_with = "idle")]
    pub together: bool,
    /// Run the users this many to a process (`muster user --count`), each still its
    /// own connection; 1 (default): a process each. Remote users, whose processes would
    /// otherwise cost more memory than the broker (about 2.3 MiB each), take up to
    /// 1,000; local ones up to 16 (the broker's cap per process).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=1000))]
    pub users_per_process: u32,
    /// With `--users-per-process`, local users: an inbox each, not one their process's
    /// users share (`muster user --own-inboxes`), to compare the two.
    #[arg(long)]
    pub own_inboxes: bool,
    /// The data systems latch their services (`muster system synthetic --latched`): a
    /// new session gets its service's newest value from the broker with its grant.
    #[arg(long)]
    pub latched: bool,
}

/// The size of a load run: how many user processes, services and systems.
#[derive(Args, Debug, Clone, Copy)]
pub struct LoadArgs {
    /// User processes.
    #[arg(long, default_value_t = 900)]
    pub users: usize,
    /// Services in the list.
    #[arg(long, default_value_t = 80)]
    pub services: usize,
    /// Systems offering them.
    #[arg(long, default_value_t = 10)]
    pub systems: usize,
}
