//! End-to-end tests of the `relight` binary on the shipped scenes: outputs
//! exist and parse, errors name what is wrong, and the lightmap pipeline
//! (atlas, receivers, dilation, bilinear lookup) agrees with per-pixel path
//! tracing.

use std::path::{Path, PathBuf};
use std::process::Command;

fn relight() -> Command {
    Command::new(env!("CARGO_BIN_EXE_relight"))
}

fn scene(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../scenes")
        .join(name)
        .join("scene.toml")
}

fn run_ok(command: &mut Command) -> String {
    let output = command.output().expect("relight runs");
    assert!(
        output.status.success(),
        "relight failed: {}\n{}",
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8(output.stdout).expect("utf-8 output")
}

fn run_err(command: &mut Command) -> String {
    let output = command.output().expect("relight runs");
    assert!(!output.status.success(), "relight should have failed");
    String::from_utf8_lossy(&output.stderr).into_owned()
}

#[test]
fn info_reports_the_cornell_box() {
    let text = run_ok(relight().args(["info", "-q"]).arg(scene("cornell-box")));
    assert!(text.contains("emissive triangles"), "{text}");
    let receivers: usize = text
        .lines()
        .find_map(|line| line.strip_prefix("receivers"))
        .map(|rest| rest.trim().parse().expect("a count"))
        .expect("a receivers line");
    assert!(receivers > 1000, "{receivers}");
}

#[test]
fn render_writes_exr_and_png() {
    let folder = tempfile::tempdir().unwrap();
    for (technique, file) in [("reference", "a.exr"), ("direct", "b.png")] {
        let output = folder.path().join(file);
        run_ok(
            relight()
                .args([
                    "render",
                    "-q",
                    "--spp",
                    "2",
                    "--technique",
                    technique,
                    "--lightmap-resolution",
                    "32",
                ])
                .arg(scene("cornell-box-point"))
                .arg("-o")
                .arg(&output),
        );
        assert!(std::fs::metadata(&output).unwrap().len() > 1000);
    }
    let image = relight_render::Image::read_exr(&folder.path().join("a.exr")).unwrap();
    assert_eq!((image.width, image.height), (256, 256));
    assert!(image
        .pixels
        .iter()
        .all(|p| p.is_finite() && p.min_element() >= 0.0));
}

#[test]
fn user_errors_name_the_culprit() {
    let missing = run_err(relight().args(["info", "-q", "no/such/scene.toml"]));
    assert!(missing.contains("no/such/scene.toml"), "{missing}");
    // The operating system's reason once, not once per link of the chain.
    assert_eq!(missing.matches("os error 2").count(), 1, "{missing}");
    let folder = tempfile::tempdir().unwrap();
    let without_mesh = folder.path().join("scene.toml");
    std::fs::write(&without_mesh, "mesh = \"absent.obj\"\n").unwrap();
    let mesh = run_err(relight().args(["info", "-q"]).arg(&without_mesh));
    assert!(mesh.contains("absent.obj"), "{mesh}");
    assert_eq!(mesh.matches("os error 2").count(), 1, "{mesh}");
    let no_paths = folder.path().join("never-written.png");
    let paths = run_err(
        relight()
            .args(["render", "-q", "--technique", "direct", "--spp", "0", "-o"])
            .arg(&no_paths)
            .arg(scene("cornell-box")),
    );
    assert!(paths.contains("--spp"), "{paths}");
    assert!(!no_paths.exists());
    let technique = run_err(
        relight()
            .args([
                "render",
                "-q",
                "--technique",
                "nonsense",
                "-o",
                "/tmp/x.png",
            ])
            .arg(scene("cornell-box")),
    );
    assert!(
        technique.contains("nonsense") && technique.contains("reference"),
        "{technique}"
    );
    let parameter = run_err(
        relight()
            .args([
                "render",
                "-q",
                "--technique",
                "reference",
                "--set",
                "samples=4",
                "-o",
                "/tmp/x.png",
            ])
            .arg(scene("cornell-box")),
    );
    assert!(parameter.contains("--set"), "{parameter}");
    let extension = run_err(
        relight()
            .args([
                "render",
                "-q",
                "--spp",
                "1",
                "--technique",
                "direct",
                "-o",
                "/tmp/relight-test.bmp",
            ])
            .arg(scene("cornell-box")),
    );
    assert!(
        extension.contains(".exr") && extension.contains(".png"),
        "{extension}"
    );
    let resolution = run_err(
        relight()
            .args(["info", "-q", "--lightmap-resolution", "3"])
            .arg(scene("cornell-box")),
    );
    assert!(resolution.contains("--lightmap-resolution"), "{resolution}");
}

#[test]
fn bench_writes_json_with_stages() {
    let folder = tempfile::tempdir().unwrap();
    let json = folder.path().join("bench.json");
    run_ok(
        relight()
            .args([
                "bench",
                "-q",
                "--technique",
                "direct",
                "--frames",
                "4",
                "--lightmap-resolution",
                "64",
                "--json",
            ])
            .arg(&json)
            .arg(scene("corridor")),
    );
    let text = std::fs::read_to_string(&json).unwrap();
    let value: serde_json::Value = serde_json::from_str(&text).unwrap();
    assert_eq!(value["frames"], 4);
    assert_eq!(value["stages"][0]["stage"], "direct lightmap");
    assert!(value["total"]["median_ms"].as_f64().unwrap() > 0.0);
    assert!(value["memory_total_bytes"].as_u64().unwrap() > 0);
    // The corridor's camera is 320x240; most pixels see its walls.
    assert_eq!(value["shading"]["stage"], "shading 320x240");
    let shaded = value["shaded_points"].as_u64().unwrap();
    assert!(shaded > 320 * 240 / 2 && shaded <= 320 * 240, "{shaded}");
}

/// Under half a budget the bench measures against an unbudgeted twin:
/// once the lights rest, the budgeted light equals the twin's within
/// 2 / 0.5 - 1 = 3 still frames (LightSkin, one bounce: exactly, as the
/// gather's own test shows), and an invalid share is refused by name.
#[test]
fn bench_measures_a_budget_against_an_unbudgeted_twin() {
    let folder = tempfile::tempdir().unwrap();
    let json = folder.path().join("bench.json");
    let args = [
        "bench",
        "-q",
        "--technique",
        "lightskin",
        "--frames",
        "6",
        "--rest-frames",
        "6",
        "--shading-resolution",
        "0x0",
        "--volume-cells",
        "0",
    ];
    let text = run_ok(
        relight()
            .args(args)
            .args(["--set", "update_budget=0.5", "--json"])
            .arg(&json)
            .arg(scene("two-rooms")),
    );
    assert!(
        text.contains("update_budget=0.5 against an unbudgeted twin"),
        "{text}"
    );
    let value: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let budget = &value["budget"];
    assert_eq!(budget["update_budget"], "0.5");
    let at_rest: Vec<f64> = budget["at_rest_percent"]
        .as_array()
        .unwrap()
        .iter()
        .map(|error| error.as_f64().unwrap())
        .collect();
    assert_eq!(at_rest.len(), 6);
    assert!(
        budget["frames_to_one_percent"].as_u64().unwrap() <= 3,
        "{budget}"
    );
    assert_eq!(*at_rest.last().unwrap(), 0.0, "{budget}");
    assert_eq!(value["rest"]["settled"], true);
    let error = run_err(
        relight()
            .args(args)
            .args(["--set", "update_budget=0"])
            .arg(scene("two-rooms")),
    );
    assert!(error.contains("update_budget"), "{error}");
}

#[test]
fn bench_shading_resolution_is_checked() {
    let error = run_err(
        relight()
            .args([
                "bench",
                "-q",
                "--technique",
                "direct",
                "--shading-resolution",
                "19x",
            ])
            .arg(scene("corridor")),
    );
    assert!(error.contains("WIDTHxHEIGHT"), "{error}");
}

#[test]
fn reference_render_is_identical_on_one_and_two_threads() {
    let folder = tempfile::tempdir().unwrap();
    let mut images = Vec::new();
    for threads in ["1", "2"] {
        let output = folder.path().join(format!("threads{threads}.exr"));
        run_ok(
            relight()
                .args([
                    "render",
                    "-q",
                    "--threads",
                    threads,
                    "--spp",
                    "2",
                    "--technique",
                    "reference",
                ])
                .arg(scene("cornell-box"))
                .arg("-o")
                .arg(&output),
        );
        images.push(std::fs::read(&output).unwrap());
    }
    assert!(
        images[0] == images[1],
        "renders differ between thread counts"
    );
}

#[test]
fn closed_stdout_is_not_an_error() {
    use std::process::Stdio;
    let mut child = relight()
        .args(["info", "-q"])
        .arg(scene("corridor"))
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // Closing our end before relight writes makes its writes fail with EPIPE.
    drop(child.stdout.take());
    let output = child.wait_with_output().unwrap();
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
}

#[test]
fn converge_sweeps_and_caches_a_reference_per_light_set() {
    let folder = tempfile::tempdir().unwrap();
    let json = folder.path().join("converge.json");
    let base = [
        "converge",
        "-q",
        "--technique",
        "direct",
        "--reference-samples",
        "4",
        "--reference-spp",
        "4",
        "--spp",
        "1",
        "--lightmap-resolution",
        "32",
    ];
    let text = run_ok(
        relight()
            .args(base)
            .arg("--cache")
            .arg(folder.path())
            .arg("--json")
            .arg(&json)
            .arg(scene("cornell-box-point")),
    );
    assert!(text.contains("image 8x8 tiles"), "{text}");
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let row = &report["settings"][0];
    // `direct` brings no indirect light: every error is exactly 100 % and
    // the light ratio 0, whatever the reference's noise.
    for key in [
        "lightmap",
        "visible_lightmap",
        "image",
        "image_tiles",
        "space",
    ] {
        assert!(
            (row[key].as_f64().unwrap() - 1.0).abs() < 1e-9,
            "{key}: {row}"
        );
    }
    assert_eq!(row["light_ratio"].as_f64().unwrap(), 0.0);
    assert!(report["visible_receivers"].as_u64().unwrap() > 0);
    let cached = || {
        std::fs::read_dir(folder.path())
            .unwrap()
            .filter(|entry| {
                entry
                    .as_ref()
                    .unwrap()
                    .file_name()
                    .to_string_lossy()
                    .starts_with("relight-reference-")
            })
            .count()
    };
    assert_eq!(cached(), 1);
    // The Cornell box with its area light shares nothing with the point-lit
    // one but the study's settings: it must get a reference of its own.
    run_ok(
        relight()
            .args(base)
            .arg("--cache")
            .arg(folder.path())
            .arg(scene("cornell-box")),
    );
    assert_eq!(cached(), 2);
    let error = run_err(
        relight()
            .args(base)
            .args(["--sweep", "order"])
            .arg(scene("cornell-box")),
    );
    assert!(error.contains("--sweep order"), "{error}");
}

/// `relight bake --shard I/4` on one thread each, then `relight merge`,
/// writes the bytes of the whole bake on all threads, for every technique
/// that bakes, each on another shipped scene; a rerun keeps a finished
/// shard, and a merge names missing or foreign shards.
/// Millions of (closest-hit, occlusion) rays on the report line that
/// starts with `label`.
fn rays_on_line(report: &str, label: &str) -> (f64, f64) {
    let line = report
        .lines()
        .find(|line| line.starts_with(label))
        .unwrap_or_else(|| panic!("no '{label}' line in {report}"));
    let number_before = |marker: &str| -> f64 {
        let end = line.find(marker).unwrap_or_else(|| panic!("{line}"));
        line[..end]
            .trim_end()
            .rsplit(' ')
            .next()
            .and_then(|word| word.parse().ok())
            .unwrap_or_else(|| panic!("{line}"))
    };
    (
        number_before(" M closest-hit"),
        number_before(" M occlusion"),
    )
}

/// The rays a bake's estimate forecast before it started against those it
/// traced: within 30 % of all of them, so that its time, which the ray
/// rates turn them into, can stay within the 50 % the estimate promises
/// (the rest is the work between rays, which varies by scene).
fn check_estimated_rays(technique: &str, report: &str) {
    let (estimated_closest, estimated_occlusion) = rays_on_line(report, "estimate");
    let (closest, occlusion) = rays_on_line(report, "rays ");
    let ratio = (estimated_closest + estimated_occlusion) / (closest + occlusion);
    assert!(
        (0.7..1.3).contains(&ratio),
        "{technique}: estimated {estimated_closest} + {estimated_occlusion} M rays, traced {closest} + {occlusion} M"
    );
}

#[test]
fn bakes_are_estimated_first_and_refused_over_the_memory_limit() {
    let folder = tempfile::tempdir().unwrap();
    let output = folder.path().join("box.bake");
    let bake = || {
        let mut command = relight();
        command
            .args(["bake", "-q", "--technique", "prm"])
            .arg(scene("cornell-box"));
        command
    };
    let error = run_err(bake().args(["--max-memory", "1M", "-o"]).arg(&output));
    assert!(
        error.contains("--max-memory")
            && error.contains("--set clusters=N")
            && error.contains("--shard"),
        "{error}"
    );
    assert!(!output.exists(), "a refused bake writes nothing");
    let estimate = run_ok(bake().arg("--estimate"));
    assert!(estimate.starts_with("estimate "), "{estimate}");
    assert!(!output.exists());
    let error = run_err(bake().args(["--max-memory", "lots", "--estimate"]));
    assert!(
        error.contains("--max-memory") && error.contains("4G"),
        "{error}"
    );
    let direct = run_ok(
        relight()
            .args(["bake", "-q", "--technique", "direct", "--estimate"])
            .arg(scene("cornell-box")),
    );
    assert!(direct.contains("no bake"), "{direct}");
}

#[test]
fn four_shards_merge_to_the_whole_bake() {
    let folder = tempfile::tempdir().unwrap();
    let path = |name: &str| folder.path().join(name);
    for (technique, scene_name) in [
        ("pic", "cornell-box"),
        ("srp", "two-rooms"),
        ("prm", "corridor"),
    ] {
        let bake = |extra: &[&str], output: &Path| {
            run_ok(
                relight()
                    .args(["bake", "-q", "--technique", technique])
                    .arg(scene(scene_name))
                    .args(extra)
                    .arg("-o")
                    .arg(output),
            )
        };
        let whole = path(&format!("{technique}.bake"));
        let report = bake(&[], &whole);
        // The report splits the time by stage and compares it with the rays.
        assert!(report.contains("outside the stages"), "{report}");
        assert!(report.contains("its rays alone need"), "{report}");
        check_estimated_rays(technique, &report);
        let parts: Vec<PathBuf> = (0..4)
            .map(|index| path(&format!("{technique}-part-{index}.bake")))
            .collect();
        // Out of order, as a job array may finish them.
        for index in [2usize, 0, 3, 1] {
            bake(
                &["--threads", "1", "--shard", &format!("{index}/4")],
                &parts[index],
            );
        }
        let merged = path(&format!("{technique}-merged.bake"));
        run_ok(
            relight()
                .args(["merge", "-q"])
                .args(parts.iter().rev())
                .arg("-o")
                .arg(&merged),
        );
        assert!(
            std::fs::read(&whole).unwrap() == std::fs::read(&merged).unwrap(),
            "{technique} on {scene_name}: the merged shards differ from the whole bake"
        );
    }

    // A rerun of the job keeps the shards that are done.
    let parts: Vec<PathBuf> = (0..4)
        .map(|index| path(&format!("prm-part-{index}.bake")))
        .collect();
    let kept = run_ok(
        relight()
            .args(["bake", "--technique", "prm", "--shard", "1/4"])
            .arg(scene("corridor"))
            .arg("-o")
            .arg(&parts[1]),
    );
    assert!(kept.contains("already baked"), "{kept}");
    let missing = run_err(
        relight()
            .args(["merge"])
            .arg(&parts[0])
            .arg(&parts[2])
            .arg("-o")
            .arg(path("x.bake")),
    );
    assert!(
        missing.contains("shards 1, 3 of 4 are missing"),
        "{missing}"
    );
    let foreign = path("foreign.bake");
    run_ok(
        relight()
            .args([
                "bake",
                "-q",
                "--technique",
                "prm",
                "--shard",
                "3/4",
                "--set",
                "entries=2048",
            ])
            .arg(scene("corridor"))
            .arg("-o")
            .arg(&foreign),
    );
    let mixed = run_err(
        relight()
            .args(["merge"])
            .args(&parts[..3])
            .arg(&foreign)
            .arg("-o")
            .arg(path("x.bake")),
    );
    assert!(mixed.contains("other bake parameters"), "{mixed}");
    // A shard is not a bake a technique loads.
    let refused = run_err(
        relight()
            .args(["render", "-q", "--technique", "prm", "--bake"])
            .arg(&parts[0])
            .arg(scene("corridor"))
            .arg("-o")
            .arg(path("x.png")),
    );
    assert!(refused.contains("relight merge"), "{refused}");
}

/// The example job files under examples/cluster run the shards and the
/// merge they promise: the Slurm submission with a stand-in `sbatch` that
/// runs each job at once (array tasks one by one), and the Kubernetes
/// Indexed Job's commands with each completion index. Both give the whole
/// bake's bytes; a rerun of the Slurm array keeps every finished shard.
#[test]
fn cluster_job_files_bake_and_merge() {
    let folder = tempfile::tempdir().unwrap();
    let root = folder.path();
    let examples = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../examples/cluster");
    let bin = root.join("bin");
    std::fs::create_dir(&bin).unwrap();
    std::os::unix::fs::symlink(env!("CARGO_BIN_EXE_relight"), bin.join("relight")).unwrap();
    let sbatch = bin.join("sbatch");
    std::fs::write(
        &sbatch,
        "#!/usr/bin/env bash\n\
         # Runs a job at once instead of queueing it.\n\
         array=''; script=''\n\
         for arg in \"$@\"; do case $arg in --array=*) array=${arg#--array=};; --*) ;; *) script=$arg;; esac; done\n\
         if [ -n \"$array\" ]; then\n\
           for i in $(seq \"${array%-*}\" \"${array#*-}\"); do SLURM_ARRAY_TASK_ID=$i bash \"$script\" >> \"$OUT/log\" || exit 1; done\n\
         else bash \"$script\" >> \"$OUT/log\" || exit 1; fi\n\
         echo 42\n",
    )
    .unwrap();
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(&sbatch, std::fs::Permissions::from_mode(0o755)).unwrap();
    let path = format!(
        "{}:{}",
        bin.display(),
        std::env::var("PATH").unwrap_or_default()
    );
    let corridor = scene("corridor");
    let whole = root.join("whole.bake");
    run_ok(
        relight()
            .args(["bake", "-q", "--technique", "prm"])
            .arg(&corridor)
            .arg("-o")
            .arg(&whole),
    );
    let whole = std::fs::read(&whole).unwrap();

    let slurm_out = root.join("slurm");
    std::fs::create_dir(&slurm_out).unwrap();
    let submit = || {
        run_ok(
            Command::new("bash")
                .arg(examples.join("slurm/submit.sh"))
                .env("PATH", &path)
                .env("SCENE", &corridor)
                .env("TECHNIQUE", "prm")
                .env("SHARDS", "4")
                .env("OUT", &slurm_out),
        )
    };
    let said = submit();
    assert!(said.contains("merge 42"), "{said}");
    assert!(
        std::fs::read(slurm_out.join("scene.bake")).unwrap() == whole,
        "Slurm merge"
    );
    submit();
    let log = std::fs::read_to_string(slurm_out.join("log")).unwrap();
    assert_eq!(log.matches("already baked").count(), 4, "{log}");

    // The Kubernetes Jobs' shell commands, with /data on the temporary folder.
    let command_of = |file: &str| {
        let text = std::fs::read_to_string(examples.join("kubernetes").join(file)).unwrap();
        let mut lines = text
            .lines()
            .skip_while(|line| !line.trim_start().starts_with("args:"));
        lines.next();
        let first = lines
            .next()
            .expect("an args entry")
            .trim()
            .trim_start_matches("- ");
        let command = if first == ">-" {
            lines
                .take_while(|line| !line.trim_start().starts_with("resources:"))
                .map(str::trim)
                .collect::<Vec<_>>()
                .join(" ")
        } else {
            first.to_string()
        };
        command.replace("/data", &root.display().to_string())
    };
    std::fs::create_dir(root.join("bakes")).unwrap();
    for index in 0..4 {
        run_ok(
            Command::new("sh")
                .args(["-c", &command_of("bake-shards.yaml")])
                .env("PATH", &path)
                .env("JOB_COMPLETION_INDEX", index.to_string())
                .env("SHARDS", "4")
                .env("TECHNIQUE", "prm")
                .env("SCENE", &corridor),
        );
    }
    run_ok(
        Command::new("sh")
            .args(["-c", &command_of("merge.yaml")])
            .env("PATH", &path),
    );
    assert!(
        std::fs::read(root.join("bakes/scene.bake")).unwrap() == whole,
        "Kubernetes merge"
    );
}

#[test]
fn gen_variants_writes_scenes_that_robustness_measures() {
    let folder = tempfile::tempdir().unwrap();
    let variants = folder.path().join("variants");
    let text = run_ok(
        relight()
            .args(["gen", "variants", "-q", "--seed", "7", "--count", "3", "-o"])
            .arg(&variants),
    );
    assert!(text.contains("wrote 3 variants"), "{text}");
    for name in ["000-room", "001-two-rooms", "002-hall"] {
        let info = run_ok(
            relight()
                .args(["info", "-q"])
                .arg(variants.join(name).join("scene.toml")),
        );
        assert!(info.contains("receivers"), "{name}: {info}");
    }
    assert!(variants.join("variants.txt").exists());
    // The same family through the study, small: two variants, few paths.
    let json = folder.path().join("robustness.json");
    let report = run_ok(
        relight()
            .args([
                "robustness",
                "-q",
                "-t",
                "lightskin",
                "--seed",
                "7",
                "--variants",
                "2",
                "--shrink",
                "4",
                "--reference-spp",
                "4",
                "--reference-samples",
                "4",
                "--cache",
            ])
            .arg(folder.path().join("cache"))
            .arg("--keep")
            .arg(folder.path().join("kept"))
            .arg("--images")
            .arg(folder.path().join("images"))
            .arg("--json")
            .arg(&json),
    );
    assert!(
        report.contains("| room | ") && report.contains("| two-rooms | "),
        "{report}"
    );
    let parsed: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let rows = parsed["rows"].as_array().unwrap();
    assert_eq!(rows.len(), 2);
    assert_eq!(rows[0]["variant"], "000-room");
    assert!(rows[0]["image_tiles"].as_f64().is_some_and(f64::is_finite));
    // Four paths a pixel cannot resolve a bound.
    assert_eq!(rows[0]["reference_resolves_bound"], false);
    // Nor the few tiles at objects' feet, if any are in view.
    assert_eq!(rows[0]["contact_resolved"], false);
    assert!(folder.path().join("images/000-room-reference.png").exists());
    let error = run_err(relight().args(["robustness", "-q", "-t", "reference", "--variants", "1"]));
    assert!(error.contains("name another technique"), "{error}");
    let error = run_err(
        relight()
            .args(["gen", "variants", "-q", "--count", "0", "-o"])
            .arg(&variants),
    );
    assert!(error.contains("choose between 1 and"), "{error}");
}
