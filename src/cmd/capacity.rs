//! `muster capacity`: an analytic queueing model of the federation, calibrated on the
//! lightest of the given stress reports and checked against the others.
//!
//! Two resources limit muster on one host:
//!
//! 1. **The broker**: one thread draining one inbox, so one FIFO server. Its arrivals
//!    are the superposition of many independent users' messages, which tends to a
//!    Poisson process (Palm–Khintchine); its service times are measured per message
//!    type and are not exponential. So: **M/G/1** with the message-type mix as a
//!    mixture — utilisation `ρ = λ·E[S]`, mean wait `W = λ·E[S²] / (2(1−ρ))`
//!    (Pollaczek–Khinchine), and the usual tail `P(wait > t) ≈ ρ·exp(−t·ρ/W)`. M/D/1
//!    would hide the measured variance; M/M/1 would invent some.
//! 2. **The CPUs**: every process shares the machine's cores. With total demand `D(N)`
//!    (broker + systems + N users, each measured in the calibration run) on `c` cores,
//!    `U = D/c`, and a processor-sharing approximation stretches every no-load step by
//!    `1/(1−U)`.
//!
//! Predicted service-request latency at N users = no-load latency (calibration run's
//! p50 minus its own broker wait, deflated by its own CPU stretch) × `1/(1−U(N))` + the
//! broker's wait at N. The p99 adds the M/G/1 wait tail at the 99th percentile and the
//! calibration run's own p99/p50 spread.

use crate::cli::CapacityArgs;
use anyhow::{bail, Context};
use serde_json::{json, Value};
use std::process::ExitCode;

/// What one stress report says, reduced to what the model needs.
struct Run {
    users: f64,
    secs: f64,
    /// Per message type: (count, mean µs, second moment µs²).
    kinds: Vec<(String, f64, f64, f64)>,
    req_p50: f64,
    req_p99: f64,
    /// After the first 10 s (the connection storm): steady state.
    steady_p50: f64,
    steady_p99: f64,
    list_p50: f64,
    broker_cpu: f64,
    systems_cpu: f64,
    users_cpu: f64,
}

fn load(path: &std::path::Path) -> anyhow::Result<Run> {
    let file = if path.is_dir() {
        path.join("report.json")
    } else {
        path.to_path_buf()
    };
    let text = std::fs::read_to_string(&file).with_context(|| file.display().to_string())?;
    let r: Value = serde_json::from_str(&text).with_context(|| file.display().to_string())?;
    let num = |v: &Value| v.as_f64().unwrap_or(0.0);
    let kinds = r["broker"]["handling"]
        .as_object()
        .with_context(|| {
            format!(
                "{}: no broker handling times (rerun `muster stress`)",
                file.display()
            )
        })?
        .iter()
        .map(|(k, v)| {
            let (mean, sd) = (num(&v["mean_us"]), num(&v["stdev_us"]));
            (k.clone(), num(&v["count"]), mean, sd * sd + mean * mean)
        })
        .collect();
    Ok(Run {
        users: num(&r["users"]),
        secs: num(&r["duration_s"]).max(1.0),
        kinds,
        req_p50: num(&r["service_request"]["p50_us"]),
        req_p99: num(&r["service_request"]["p99_us"]),
        steady_p50: num(&r["service_request_after_10s"]["p50_us"]),
        steady_p99: num(&r["service_request_after_10s"]["p99_us"]),
        list_p50: num(&r["list"]["p50_us"]),
        broker_cpu: num(&r["cpu"]["broker_percent"]),
        systems_cpu: num(&r["cpu"]["systems_percent"]),
        users_cpu: num(&r["cpu"]["users_percent_first_half"]),
    })
}

/// The model, calibrated on one run.
struct Model {
    /// Per user: messages per second of each type, with their E[S], E[S²] (µs, µs²).
    per_user: Vec<(f64, f64, f64)>,
    cores: f64,
    base_cpu: f64,
    user_cpu: f64,
    no_load_p50: f64,
    spread_p99: f64,
}

struct Prediction {
    rho: f64,
    cpu: f64,
    wait_mean: f64,
    p50: f64,
    p99: f64,
}

impl Model {
    fn calibrate(c: &Run, cores: f64) -> Self {
        let per_user = c
            .kinds
            .iter()
            .map(|(_, n, m, m2)| (n / c.secs / c.users.max(1.0), *m, *m2))
            .collect();
        let mut m = Model {
            per_user,
            cores,
            base_cpu: (c.broker_cpu + c.systems_cpu) / 100.0,
            user_cpu: c.users_cpu / 100.0 / c.users.max(1.0),
            no_load_p50: 0.0,
            spread_p99: 0.0,
        };
        let at = m.queue(c.users);
        let stretch = 1.0 / (1.0 - m.cpu(c.users)).max(0.05);
        m.no_load_p50 = ((c.req_p50 - at.1).max(1.0)) / stretch;
        m.spread_p99 = (c.req_p99 / c.req_p50.max(1.0)).max(1.0);
        m
    }

    fn cpu(&self, n: f64) -> f64 {
        (self.base_cpu + n * self.user_cpu) / self.cores
    }

    /// (ρ, mean wait µs, wait p99 µs) of the broker at `n` users.
    fn queue(&self, n: f64) -> (f64, f64, f64) {
        // λ·E[S] and λ·E[S²], with λ per µs.
        let es: f64 = self.per_user.iter().map(|(r, m, _)| r * n * m).sum::<f64>() / 1e6;
        let es2: f64 = self
            .per_user
            .iter()
            .map(|(r, _, m2)| r * n * m2)
            .sum::<f64>()
            / 1e6;
        let rho = es;
        if rho >= 1.0 {
            return (rho, f64::INFINITY, f64::INFINITY);
        }
        let w = es2 / (2.0 * (1.0 - rho));
        let p99 = if rho > 0.01 && w > 0.0 {
            (w / rho) * (100.0 * rho).ln()
        } else {
            0.0
        };
        (rho, w, p99)
    }

    fn predict(&self, n: f64) -> Prediction {
        let (rho, w, w99) = self.queue(n);
        let cpu = self.cpu(n);
        let stretch = if cpu < 0.95 {
            1.0 / (1.0 - cpu)
        } else {
            f64::INFINITY
        };
        let p50 = self.no_load_p50 * stretch + w;
        Prediction {
            rho,
            cpu,
            wait_mean: w,
            p50,
            p99: self.no_load_p50 * stretch * self.spread_p99 + w99,
        }
    }

    /// Users at which the first resource saturates.
    fn saturation(&self) -> (f64, &'static str) {
        let broker: f64 = 1e6
            / self
                .per_user
                .iter()
                .map(|(r, m, _)| r * m)
                .sum::<f64>()
                .max(1e-12);
        let cpu = (self.cores - self.base_cpu) / self.user_cpu.max(1e-12);
        if broker < cpu {
            (broker, "broker (M/G/1 utilisation reaches 1)")
        } else {
            (cpu, "CPU (all cores busy)")
        }
    }
}

pub fn run(a: CapacityArgs) -> anyhow::Result<ExitCode> {
    if a.reports.is_empty() {
        bail!("give at least one stress report (report.json or its folder)");
    }
    let mut runs: Vec<Run> = a
        .reports
        .iter()
        .map(|p| load(p))
        .collect::<anyhow::Result<_>>()?;
    runs.sort_by(|x, y| x.users.total_cmp(&y.users));
    let cores = a
        .cores
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1.0, |n| n.get() as f64));
    let m = Model::calibrate(&runs[0], cores);
    let mut rows = Vec::new();
    for r in &runs {
        let p = m.predict(r.users);
        rows.push(json!({
            "users": r.users, "measured": true,
            "broker_utilisation": p.rho, "cpu_utilisation": p.cpu, "broker_wait_us": p.wait_mean,
            "predicted_p50_us": p.p50, "measured_p50_us": r.req_p50,
            "predicted_p99_us": p.p99, "measured_p99_us": r.req_p99,
            "measured_steady_p50_us": r.steady_p50, "measured_steady_p99_us": r.steady_p99,
            "error_p50": (p.p50 - r.req_p50) / r.req_p50.max(1.0),
            "error_p99": (p.p99 - r.req_p99) / r.req_p99.max(1.0),
            "error_steady_p50": (p.p50 - r.steady_p50) / r.steady_p50.max(1.0),
            "error_steady_p99": (p.p99 - r.steady_p99) / r.steady_p99.max(1.0),
            "list_p50_us": r.list_p50,
        }));
    }
    for n in &a.users {
        let p = m.predict(*n as f64);
        rows.push(json!({
            "users": n, "measured": false,
            "broker_utilisation": p.rho, "cpu_utilisation": p.cpu, "broker_wait_us": p.wait_mean,
            "predicted_p50_us": p.p50, "predicted_p99_us": p.p99,
        }));
    }
    let (sat, by) = m.saturation();
    let out = json!({
        "model": "broker M/G/1 (Pollaczek-Khinchine) + processor sharing on the cores",
        "calibrated_on_users": runs[0].users, "cores": cores,
        "per_user_messages_per_s": m.per_user.iter().map(|(r, _, _)| r).sum::<f64>(),
        "no_load_service_request_us": m.no_load_p50,
        "saturation_users": sat, "saturated_by": by,
        "rows": rows,
    });
    if a.json {
        println!("{out}");
        return Ok(ExitCode::SUCCESS);
    }
    println!(
        "capacity model: broker M/G/1 + processor sharing on {cores} cores, calibrated on the {}-user run",
        runs[0].users
    );
    println!(
        "per user {:.2} broker messages/s; no-load service request {:.0} µs; saturates at about {:.0} users: {by}",
        out["per_user_messages_per_s"].as_f64().unwrap_or(0.0),
        m.no_load_p50,
        sat
    );
    println!("(measured: the whole run / after its first 10 s, when every user is connected)");
    println!(
        "\n{:>7} {:>9} {:>8} {:>9} {:>9} {:>15} {:>9} {:>17}",
        "users", "broker ρ", "CPU U", "wait µs", "p50 pred", "p50 meas", "p99 pred", "p99 meas"
    );
    for r in &rows {
        let f = |k: &str| r[k].as_f64().map_or("-".to_string(), |v| format!("{v:.0}"));
        let both = |a: &str, b: &str| match r[b].as_f64() {
            Some(_) => format!("{} / {}", f(a), f(b)),
            None => f(a),
        };
        println!(
            "{:>7} {:>9.4} {:>8.3} {:>9.1} {:>9} {:>15} {:>9} {:>17}",
            r["users"].as_f64().unwrap_or(0.0),
            r["broker_utilisation"].as_f64().unwrap_or(0.0),
            r["cpu_utilisation"].as_f64().unwrap_or(0.0),
            r["broker_wait_us"].as_f64().unwrap_or(0.0),
            f("predicted_p50_us"),
            both("measured_p50_us", "measured_steady_p50_us"),
            f("predicted_p99_us"),
            both("measured_p99_us", "measured_steady_p99_us"),
        );
    }
    Ok(ExitCode::SUCCESS)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run(users: f64, req_p50: f64) -> Run {
        Run {
            users,
            secs: 10.0,
            // 2 requests/s/user at 10 µs (constant), 1 hello/s/user at 20 µs.
            kinds: vec![
                ("request".into(), 2.0 * 10.0 * users, 10.0, 100.0),
                ("hello".into(), 10.0 * users, 20.0, 400.0),
            ],
            req_p50,
            req_p99: 2.0 * req_p50,
            steady_p50: req_p50,
            steady_p99: 2.0 * req_p50,
            list_p50: 5.0,
            broker_cpu: 1.0,
            systems_cpu: 1.0,
            users_cpu: 0.1 * users,
        }
    }

    #[test]
    fn pollaczek_khinchine_and_saturation() {
        let m = Model::calibrate(&run(100.0, 200.0), 2.0);
        // λ per user = 3/s; E[S] mix = (2·10 + 1·20)/3 µs; ρ(n) = n·40e-6.
        let (rho, w, _) = m.queue(1000.0);
        assert!((rho - 0.04).abs() < 1e-9, "{rho}");
        // W = λE[S²]/(2(1-ρ)) = 1000·(2·100 + 400)e-6 / (2·0.96) µs.
        assert!((w - 0.6 / 1.92).abs() < 1e-9, "{w}");
        let (sat, by) = m.saturation();
        // CPU: (2 - 0.02) / 0.001 = 1980 users; broker: 1e6/40 = 25000.
        assert!((sat - 1980.0).abs() < 1e-6, "{sat}");
        assert!(by.starts_with("CPU"));
        // More users never predict less latency.
        assert!(m.predict(1500.0).p50 > m.predict(100.0).p50);
        assert!(m.predict(5000.0).p50.is_infinite());
    }
}
