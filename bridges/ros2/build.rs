//! Compiles the built-in ROS 2 message definitions (`msg/<pkg>/<Type>.msg`) into a table.

use std::fmt::Write as _;
use std::path::Path;

fn main() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("msg");
    println!("cargo:rerun-if-changed={}", root.display());
    let mut entries = Vec::new();
    let mut pkgs: Vec<_> = std::fs::read_dir(&root)
        .expect("msg/")
        .filter_map(Result::ok)
        .filter(|e| e.path().is_dir())
        .collect();
    pkgs.sort_by_key(|e| e.file_name());
    for pkg in pkgs {
        let mut files: Vec<_> = std::fs::read_dir(pkg.path())
            .expect("package dir")
            .filter_map(Result::ok)
            .filter(|e| e.path().extension().is_some_and(|x| x == "msg"))
            .collect();
        files.sort_by_key(|e| e.file_name());
        for f in files {
            let path = f.path();
            println!("cargo:rerun-if-changed={}", path.display());
            let ty = path
                .file_stem()
                .expect("stem")
                .to_string_lossy()
                .to_string();
            entries.push((
                format!("{}/msg/{ty}", pkg.file_name().to_string_lossy()),
                path.display().to_string(),
            ));
        }
    }
    let mut out = String::from(
        "/// The built-in definitions: (`pkg/msg/Type`, the `.msg` text).\npub static BUILTIN: &[(&str, &str)] = &[\n",
    );
    for (ty, path) in entries {
        writeln!(out, "    ({ty:?}, include_str!({path:?})),").expect("write");
    }
    out.push_str("];\n");
    let dest = Path::new(&std::env::var("OUT_DIR").expect("OUT_DIR")).join("builtin_msgs.rs");
    std::fs::write(dest, out).expect("write builtin_msgs.rs");
}
