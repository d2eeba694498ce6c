//! Hostile mesh files: counts the bytes do not hold, glTF nodes in a cycle, a million
//! levels deep or shared by two parents, a line of 500 MB, and a file of each format cut
//! short. Each is refused with one line naming the object, the file and, where the
//! format has them, the line or the record; without a panic, within seconds, and
//! without allocating much more than the file (or than the renderer's triangle limit
//! allows).
//!
//! Each file is read by this test binary started again (the child below) under a
//! virtual memory limit and a time limit, so that a reader that loops or allocates
//! without bound fails its test instead of the machine; the child reports its error
//! and its peak resident memory (`VmHWM`) before and after reading.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use render::limits::MAX_MESH_TRIANGLES;
use render::{parse_scene_with, MeshFiles};

use crate::mesh_support::{
    cow, glb, gltf, obj, ply_ascii, ply_binary, stl_ascii, stl_binary, TempDir,
};

/// The variable that makes the child read one file: its path.
const CASE: &str = "TESSERA_HOSTILE_MESH_FILE";
/// The line the child reports on.
const REPORT: &str = "hostile-mesh-report ";
/// The child's address space: far more than any refusal here needs, far less than the
/// machine has.
const ADDRESS_SPACE_KIB: u64 = 4 << 20;

/// What the child saw.
#[derive(Debug)]
struct Report {
    /// The error, cut to its first 2,000 bytes, or `None` if the scene loaded.
    error: Option<String>,
    /// The error's whole length in bytes, and its number of lines.
    error_len: usize,
    error_lines: usize,
    millis: u64,
    /// The peak resident memory before and after reading, in KiB.
    peak_before_kib: u64,
    peak_after_kib: u64,
}

fn peak_resident_kib() -> u64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .unwrap_or(0)
}

/// A scene of one mesh object naming `path`.
fn scene_naming(path: &Path) -> String {
    let file = serde_json::to_string(path.to_str().expect("test paths are UTF-8")).unwrap();
    format!(
        r#"{{"lights": [{{"position": "0 5 -5", "color": "1 1 1"}}],
  "objects": [{{"type": "mesh", "file": {file}, "color": "0.5 0.5 0.5 0"}}]}}"#
    )
}

/// The child: reads the scene naming the file of [`CASE`] and reports on one line.
/// Without [`CASE`] (an ordinary test run) it does nothing.
#[test]
fn child_reads_one_hostile_file() {
    let Ok(path) = std::env::var(CASE) else {
        return;
    };
    let path = PathBuf::from(path);
    let text = scene_naming(&path);
    let before = peak_resident_kib();
    let started = Instant::now();
    let result = parse_scene_with(&text, &MeshFiles::beside(path.parent().unwrap()));
    let millis = started.elapsed().as_millis() as u64;
    let after = peak_resident_kib();
    let report = match result {
        Ok(_) => serde_json::json!({"error": null, "error_len": 0, "error_lines": 0}),
        Err(e) => {
            let e = e.to_string();
            let mut cut = e.len().min(2000);
            while !e.is_char_boundary(cut) {
                cut -= 1;
            }
            serde_json::json!({
                "error": &e[..cut],
                "error_len": e.len(),
                "error_lines": e.lines().count(),
            })
        }
    };
    let mut report = report;
    report["millis"] = millis.into();
    report["before"] = before.into();
    report["after"] = after.into();
    println!("\n{REPORT}{report}");
}

/// Reads the file at `path` in a child limited to [`ADDRESS_SPACE_KIB`] and `timeout`.
fn read_in_child(path: &Path, timeout: Duration) -> Report {
    let exe = std::env::current_exe().unwrap();
    let mut child = Command::new("sh")
        .arg("-c")
        .arg(r#"ulimit -v "$1" && shift && exec "$@""#)
        .arg("sh")
        .arg(ADDRESS_SPACE_KIB.to_string())
        .arg(exe)
        .args([
            "--exact",
            "hostile_meshes::child_reads_one_hostile_file",
            "--nocapture",
            "--test-threads",
            "1",
        ])
        .env(CASE, path)
        .env("RUST_BACKTRACE", "0")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("the test binary starts again");
    let started = Instant::now();
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if started.elapsed() > timeout {
            child.kill().unwrap();
            child.wait().unwrap();
            panic!(
                "{}: still reading after {timeout:?}: killed",
                path.display()
            );
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let out = child.wait_with_output().unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    let line = stdout
        .lines()
        .find_map(|l| l.split_once(REPORT).map(|(_, report)| report))
        .unwrap_or_else(|| {
            panic!(
                "{}: the child ended ({status}) without a report; stderr:\n{stderr}",
                path.display()
            )
        });
    assert!(
        status.success(),
        "{}: the child failed ({status}): {stderr}",
        path.display()
    );
    let v: serde_json::Value = serde_json::from_str(line).unwrap();
    Report {
        error: v["error"].as_str().map(str::to_owned),
        error_len: v["error_len"].as_u64().unwrap() as usize,
        error_lines: v["error_lines"].as_u64().unwrap() as usize,
        millis: v["millis"].as_u64().unwrap(),
        peak_before_kib: v["before"].as_u64().unwrap(),
        peak_after_kib: v["after"].as_u64().unwrap(),
    }
}

/// Asserts that the file at `path` is refused in one line that names the object and
/// the file and ends with `end` (or contains it, with `anywhere`), within `seconds`, its
/// peak memory growing by at most `memory_kib`; the error.
#[track_caller]
fn assert_refused(path: &Path, end: &str, seconds: u64, memory_kib: u64) -> String {
    let report = read_in_child(path, Duration::from_secs(seconds));
    let name = path.display();
    let error = report
        .error
        .unwrap_or_else(|| panic!("{name}: loaded, expected a refusal ending {end:?}"));
    assert!(
        report.error_lines == 1 && report.error_len < 1000,
        "{name}: one short line, got {} lines, {} bytes: {error:?}",
        report.error_lines,
        report.error_len
    );
    let prefix = format!("objects[0].file: {name}: ");
    assert!(
        error.starts_with(&prefix) && error.ends_with(end),
        "{name}: expected {prefix:?} … {end:?}, got {error:?}"
    );
    assert!(
        report.millis < seconds * 1000,
        "{name}: refused in {} ms",
        report.millis
    );
    let grew = report.peak_after_kib.saturating_sub(report.peak_before_kib);
    eprintln!(
        "{name}: refused in {} ms, peak memory {} KiB more than before reading",
        report.millis, grew
    );
    assert!(
        grew <= memory_kib,
        "{name}: the peak memory grew by {grew} KiB reading it, more than {memory_kib} KiB"
    );
    error
}

/// Small files: refused within 20 s (a few milliseconds on any machine, but the child
/// shares two cores with the other tests), in 64 MiB more than the test's own memory.
const QUICK: u64 = 20;
const SMALL_KIB: u64 = 64 << 10;

// ---------------------------------------------------------------------------------
// Counts the bytes do not hold.
// ---------------------------------------------------------------------------------

#[test]
fn a_ply_claiming_a_trillion_vertices_is_refused_at_the_first_missing_one() {
    let dir = TempDir::new("hostile-ply");
    let header = |format: &str| {
        format!(
            "ply\nformat {format} 1.0\nelement vertex 1000000000000\nproperty double x\n\
             property double y\nproperty double z\nelement face 1000000000000\n\
             property list uint uint vertex_indices\nend_header\n"
        )
    };
    let mut binary = header("binary_little_endian").into_bytes();
    for x in [0.0f64, 1.0, 2.0, 3.0, 4.0] {
        binary.extend_from_slice(&x.to_le_bytes());
    }
    let path = dir.write("trillion.ply", &binary);
    assert_refused(
        &path,
        "record 2: vertex 2 of 1000000000000: the file ends before it",
        QUICK,
        SMALL_KIB,
    );
    let ascii = header("ascii") + "0 0 0\n1 0 0\n";
    let path = dir.write("trillion-ascii.ply", ascii.as_bytes());
    assert_refused(
        &path,
        "line 12: vertex 3 of 1000000000000: the file ends before it",
        QUICK,
        SMALL_KIB,
    );
    // Faces claiming twenty million corners (as many as a face within the triangle
    // limit may have) and four billion, in files of a few bytes.
    for (corners, end) in [
        (
            20_000_000u32,
            "record 4: face 1 of 1: the file ends before it".to_owned(),
        ),
        (
            u32::MAX,
            format!(
                "record 4: face 1 of 1: a list of 4294967295 items, more than the {} of a \
                 face within the limit of {MAX_MESH_TRIANGLES} triangles",
                MAX_MESH_TRIANGLES + 2
            ),
        ),
    ] {
        let mut list = b"ply\nformat binary_big_endian 1.0\nelement vertex 3\n\
                         property float x\nproperty float y\nproperty float z\n\
                         element face 1\nproperty list uint uint vertex_indices\nend_header\n"
            .to_vec();
        for x in [0.0f32, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0] {
            list.extend_from_slice(&x.to_be_bytes());
        }
        list.extend_from_slice(&corners.to_be_bytes());
        for i in [0u32, 1, 2] {
            list.extend_from_slice(&i.to_be_bytes());
        }
        let path = dir.write(&format!("{corners}-corners.ply"), &list);
        assert_refused(&path, &end, QUICK, SMALL_KIB);
    }
}

#[test]
fn a_binary_stl_whose_count_exceeds_its_bytes_is_not_believed() {
    let Some(cow) = cow() else { return };
    let dir = TempDir::new("hostile-stl");
    // Four billion facets claimed, the cow's 5,804 there: not a binary STL by its size,
    // and not text.
    let mut lie = stl_binary(cow);
    lie[80..84].copy_from_slice(&u32::MAX.to_le_bytes());
    let path = dir.write("lie.stl", &lie);
    let error = assert_refused(&path, "", QUICK, SMALL_KIB);
    assert!(
        error.contains("neither a binary STL (its size is not 84 + 50 × its facet count) nor text"),
        "{error}"
    );
    // The same lie in a header that starts with `solid`, as some exporters write binary
    // files, facets of zeros (valid text): read as an ASCII STL without a facet.
    let mut solid = b"solid lie".to_vec();
    solid.resize(80, b' ');
    solid.extend_from_slice(&1_000_000_000u32.to_le_bytes());
    solid.resize(84 + 50 * 100, 0);
    let path = dir.write("solid-lie.stl", &solid);
    assert_refused(
        &path,
        "no triangle that is not degenerate: nothing to hit",
        QUICK,
        SMALL_KIB,
    );
}

// ---------------------------------------------------------------------------------
// glTF node graphs.
// ---------------------------------------------------------------------------------

/// A `.gltf` of one triangle (mesh 0) and the nodes and roots given.
fn gltf_with_nodes(nodes: &str, roots: &str) -> String {
    use base64::Engine;
    let mut bytes = Vec::new();
    for x in [0.0f32, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0] {
        bytes.extend_from_slice(&x.to_le_bytes());
    }
    let data = base64::engine::general_purpose::STANDARD.encode(&bytes);
    format!(
        r#"{{"asset": {{"version": "2.0"}}, "scene": 0, "scenes": [{{"nodes": {roots}}}],
"nodes": {nodes},
"meshes": [{{"primitives": [{{"attributes": {{"POSITION": 0}}}}]}}],
"buffers": [{{"byteLength": 36, "uri": "data:application/octet-stream;base64,{data}"}}],
"bufferViews": [{{"buffer": 0, "byteLength": 36}}],
"accessors": [{{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3"}}]}}"#
    )
}

#[test]
fn gltf_node_cycles_are_refused() {
    let dir = TempDir::new("hostile-gltf-cycles");
    let cases = [
        (
            r#"[{"mesh": 0, "children": [0]}]"#,
            "[0]",
            "nodes[0] is its own ancestor: a cycle",
        ),
        (
            r#"[{"children": [1]}, {"children": [2]}, {"mesh": 0, "children": [1]}]"#,
            "[0]",
            "nodes[1] is its own ancestor: a cycle",
        ),
    ];
    for (k, (nodes, roots, end)) in cases.iter().enumerate() {
        let path = dir.write(
            &format!("cycle-{k}.gltf"),
            gltf_with_nodes(nodes, roots).as_bytes(),
        );
        assert_refused(&path, end, QUICK, SMALL_KIB);
    }
}

#[test]
fn a_million_nested_gltf_levels_are_refused() {
    let dir = TempDir::new("hostile-gltf-deep");
    // A chain of a million nodes, each the child of the one before.
    let mut nodes = String::from("[");
    for i in 1..1_000_000 {
        nodes += &format!(r#"{{"children": [{i}]}},"#);
    }
    nodes += r#"{"mesh": 0}]"#;
    let path = dir.write("chain.gltf", gltf_with_nodes(&nodes, "[0]").as_bytes());
    // The document is held in memory as a JSON tree first: some 850 bytes a node, 50
    // times the file (17 MB).
    assert_refused(&path, "nodes deeper than 64 levels", 60, 1 << 20);
    // JSON nested a million levels deep (in `extras`, which nothing reads).
    let deep = format!(
        r#"{{"asset": {{"version": "2.0"}}, "extras": {}{}}}"#,
        "[".repeat(1_000_000),
        "]".repeat(1_000_000)
    );
    let path = dir.write("nested.gltf", deep.as_bytes());
    assert_refused(
        &path,
        "line 1: recursion limit exceeded at line 1 column 167",
        QUICK,
        SMALL_KIB,
    );
    // The same in a GLB's JSON chunk.
    let mut json = deep.into_bytes();
    while json.len() % 4 != 0 {
        json.push(b' ');
    }
    let mut bytes = b"glTF".to_vec();
    bytes.extend_from_slice(&2u32.to_le_bytes());
    bytes.extend_from_slice(&((20 + json.len()) as u32).to_le_bytes());
    bytes.extend_from_slice(&(json.len() as u32).to_le_bytes());
    bytes.extend_from_slice(b"JSON");
    bytes.extend_from_slice(&json);
    let path = dir.write("nested.glb", &bytes);
    assert_refused(
        &path,
        "the GLB's JSON: recursion limit exceeded at line 1 column 167",
        QUICK,
        SMALL_KIB,
    );
}

#[test]
fn gltf_nodes_shared_by_two_parents_are_refused() {
    // 60 levels, each node listing the next twice: no cycle, no level deeper than 64,
    // and 2^60 paths to the last node. A node has one parent at most (glTF 2.0): a
    // node reached twice is refused, not walked again.
    let dir = TempDir::new("hostile-gltf-shared");
    let mut nodes: Vec<String> = (1..60)
        .map(|i| format!(r#"{{"children": [{i}, {i}]}}"#))
        .collect();
    nodes.push(r#"{"mesh": 0}"#.into());
    let path = dir.write(
        "lattice.gltf",
        gltf_with_nodes(&format!("[{}]", nodes.join(",")), "[0]").as_bytes(),
    );
    assert_refused(
        &path,
        "nodes[59] is reached a second time: a node has at most one parent",
        QUICK,
        SMALL_KIB,
    );
    // A root listed twice.
    let path = dir.write(
        "twice.gltf",
        gltf_with_nodes(r#"[{"mesh": 0}]"#, "[0, 0]").as_bytes(),
    );
    assert_refused(
        &path,
        "nodes[0] is reached a second time: a node has at most one parent",
        QUICK,
        SMALL_KIB,
    );
}

#[test]
fn a_gltf_primitive_shown_by_many_nodes_is_held_to_the_triangle_limit() {
    // One primitive of 100,000 positions and as many triangles (1.6 MB), shown by 2,000
    // nodes: 200 million triangles, ten times the limit, from a file of 1.7 MB. Refused
    // once the limit is reached, having held no more than its triangles (24 bytes each
    // with their corners' normals) and their positions (24 bytes each).
    let dir = TempDir::new("hostile-gltf-many");
    let n = 100_000u32;
    let mut buffer = Vec::new();
    for k in 0..n {
        for x in [k as f32, (k % 7) as f32, (k % 3) as f32] {
            buffer.extend_from_slice(&x.to_le_bytes());
        }
    }
    let positions = buffer.len();
    for t in 0..n {
        for i in [t, (t + 1) % n, (t + 2) % n] {
            buffer.extend_from_slice(&i.to_le_bytes());
        }
    }
    let nodes = vec![r#"{"mesh": 0}"#; 2000].join(",");
    let roots: Vec<String> = (0..2000).map(|i| i.to_string()).collect();
    let json = format!(
        r#"{{"asset": {{"version": "2.0"}}, "scenes": [{{"nodes": [{}]}}], "nodes": [{nodes}],
"meshes": [{{"primitives": [{{"attributes": {{"POSITION": 0}}, "indices": 1}}]}}],
"buffers": [{{"byteLength": {}}}],
"bufferViews": [{{"buffer": 0, "byteLength": {positions}}},
                {{"buffer": 0, "byteOffset": {positions}, "byteLength": {}}}],
"accessors": [{{"bufferView": 0, "componentType": 5126, "count": {n}, "type": "VEC3"}},
              {{"bufferView": 1, "componentType": 5125, "count": {}, "type": "SCALAR"}}]}}"#,
        roots.join(","),
        buffer.len(),
        buffer.len() - positions,
        3 * n
    );
    let mut json = json.into_bytes();
    while json.len() % 4 != 0 {
        json.push(b' ');
    }
    let mut glb = b"glTF".to_vec();
    glb.extend_from_slice(&2u32.to_le_bytes());
    glb.extend_from_slice(&((28 + json.len() + buffer.len()) as u32).to_le_bytes());
    glb.extend_from_slice(&(json.len() as u32).to_le_bytes());
    glb.extend_from_slice(b"JSON");
    glb.extend_from_slice(&json);
    glb.extend_from_slice(&(buffer.len() as u32).to_le_bytes());
    glb.extend_from_slice(b"BIN\0");
    glb.extend_from_slice(&buffer);
    let path = dir.write("many.glb", &glb);
    let held_kib = (MAX_MESH_TRIANGLES as u64 * 48) / 1024;
    assert_refused(
        &path,
        &format!(
            "meshes[0].primitives[0]: accessors[1]: 300000 elements, more than the limit of \
             {MAX_MESH_TRIANGLES} triangles leaves room for"
        ),
        120,
        held_kib + (256 << 10),
    );
}

#[test]
fn a_gltf_offset_past_the_end_of_numbers_is_refused() {
    // An accessor's byteOffset of 2^64 − 1: its end wraps around past zero.
    let dir = TempDir::new("hostile-gltf-offset");
    let text = gltf_with_nodes(r#"[{"mesh": 0}]"#, "[0]").replace(
        r#""count": 3, "type": "VEC3""#,
        r#""count": 3, "byteOffset": 18446744073709551615, "type": "VEC3""#,
    );
    let path = dir.write("offset.gltf", text.as_bytes());
    assert_refused(
        &path,
        "meshes[0].primitives[0]: accessors[0]: 3 elements do not fit in their buffer view",
        QUICK,
        SMALL_KIB,
    );
}

// ---------------------------------------------------------------------------------
// One line of 500 MB.
// ---------------------------------------------------------------------------------

/// Writes `head`, then `fill` repeated to 500 MB, then `tail`, streaming.
fn huge_file(path: &Path, head: &[u8], fill: &[u8], tail: &[u8]) -> u64 {
    const SIZE: usize = 500 << 20;
    let mut out = std::io::BufWriter::with_capacity(1 << 20, std::fs::File::create(path).unwrap());
    out.write_all(head).unwrap();
    let chunk = fill.repeat((1 << 20) / fill.len());
    let mut written = head.len();
    while written < SIZE {
        out.write_all(&chunk).unwrap();
        written += chunk.len();
    }
    out.write_all(tail).unwrap();
    out.flush().unwrap();
    (written + tail.len()) as u64
}

#[test]
fn an_obj_line_of_500_mb_is_refused_in_one_short_line() {
    let dir = TempDir::new("hostile-obj-line");
    let path = dir.path().join("line.obj");
    // A number of 500 million digits: refused on line 1, the number not repeated whole.
    let size = huge_file(&path, b"v 0 0 ", b"1234567890", b"\nf 1 1 1\n");
    let error = assert_refused(
        &path,
        "is not a finite number",
        120,
        size / 1024 + (64 << 10),
    );
    assert!(error.contains(": line 1: \"1234567890"), "{error}");
    std::fs::remove_file(&path).unwrap();

    // A face of 250 million corners: its fan would be 250 million triangles, more than
    // the limit, refused before they are all made.
    let size = huge_file(&path, b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3", b" 2 3", b"\n");
    // The triangles up to the limit (12 bytes each, and their corners' normals as many),
    // twice over while their vectors grow.
    let triangles_kib = (MAX_MESH_TRIANGLES as u64 * 24 * 2) / 1024;
    assert_refused(
        &path,
        &format!("line 4: more than the limit of {MAX_MESH_TRIANGLES} triangles"),
        120,
        size / 1024 + triangles_kib + (64 << 10),
    );
}

// ---------------------------------------------------------------------------------
// Files cut short.
// ---------------------------------------------------------------------------------

/// `bytes` cut just after the `n`-th occurrence of `pattern` (and `extra` bytes more).
fn cut_after(bytes: &[u8], pattern: &[u8], n: usize, extra: usize) -> Vec<u8> {
    let at = bytes
        .windows(pattern.len())
        .enumerate()
        .filter(|(_, w)| *w == pattern)
        .nth(n)
        .map(|(i, _)| i + pattern.len() + extra)
        .expect("the pattern occurs");
    bytes[..at].to_vec()
}

fn lines_in(bytes: &[u8]) -> usize {
    bytes.iter().filter(|&&b| b == b'\n').count() + 1
}

#[test]
fn a_file_of_each_format_cut_short_is_refused_naming_where() {
    let Some(cow) = cow() else { return };
    let single = cow.rounded_to_f32();
    let dir = TempDir::new("hostile-cut");

    // OBJ: cut inside a face line, after its first corner.
    let cut = cut_after(&obj(cow, false), b"\nf ", 1000, 1);
    let line = lines_in(&cut);
    let path = dir.write("cut.obj", &cut);
    let error = assert_refused(
        &path,
        "a face of 1 vertices: a face has at least 3",
        QUICK,
        SMALL_KIB,
    );
    assert!(error.contains(&format!(": line {line}: ")), "{error}");

    // ASCII PLY: cut in the faces.
    let cut = cut_after(&ply_ascii(cow), b"\n3 ", 2000, 0);
    let path = dir.write("cut-ascii.ply", &cut);
    let error = assert_refused(&path, "", QUICK, SMALL_KIB);
    assert!(
        error.contains(&format!(": line {}: face 2001 of 5804: ", lines_in(&cut))),
        "{error}"
    );

    // Binary PLY, both byte orders: cut in the vertices (a record is a vertex or face).
    for (name, big) in [("cut-little.ply", false), ("cut-big.ply", true)] {
        let whole = ply_binary(cow, big, false);
        let header = cut_after(&whole, b"end_header\n", 0, 0).len();
        let cut = whole[..header + 24 * 1000 + 7].to_vec();
        let path = dir.write(name, &cut);
        assert_refused(
            &path,
            "record 1001: vertex 1001 of 2904: the file ends before it",
            QUICK,
            SMALL_KIB,
        );
    }

    // Binary STL: its size no longer that of its count, and not text.
    let whole = stl_binary(&single);
    let path = dir.write("cut-binary.stl", &whole[..whole.len() - 31]);
    let error = assert_refused(&path, "", QUICK, SMALL_KIB);
    assert!(error.contains("neither a binary STL"), "{error}");

    // ASCII STL: cut inside a facet's loop.
    let cut = cut_after(&stl_ascii(&single), b"outer loop\n", 300, 0);
    let opened = lines_in(&cut) - 1;
    let path = dir.write("cut-ascii.stl", &cut);
    assert_refused(
        &path,
        &format!("line {opened}: a loop never closed (`endloop`): the file is cut short"),
        QUICK,
        SMALL_KIB,
    );

    // glTF: its JSON cut in the middle.
    let whole = gltf(&single);
    let cut = &whole[..whole.len() / 2];
    let path = dir.write("cut.gltf", cut);
    let error = assert_refused(&path, "", QUICK, SMALL_KIB);
    assert!(
        error.contains(&format!(": line {}: EOF while parsing", lines_in(cut))),
        "{error}"
    );

    // GLB: its binary chunk cut.
    let whole = glb(&single);
    let path = dir.write("cut.glb", &whole[..whole.len() - 1000]);
    let error = assert_refused(&path, "goes past the end", QUICK, SMALL_KIB);
    assert!(error.contains("a GLB chunk of "), "{error}");
}
