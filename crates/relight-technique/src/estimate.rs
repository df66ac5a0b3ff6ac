//! What a bake will cost, told before it starts: its rays (turned into time
//! at the rate the scene's own BVH traces them) and the memory it holds at
//! its peak beyond the loaded scene, so that a bake that cannot fit is
//! refused at once instead of failing an hour in.

use relight_trace::counters::RayCount;

/// A technique's forecast of one bake (whole or one shard), made from the
/// scene's counts and the parameters, without baking.
#[derive(Clone, Debug, PartialEq)]
pub struct BakeEstimate {
    /// Rays the bake will trace.
    pub rays: RayCount,
    /// The bake's time over its rays' own time at the scene's measured ray
    /// rates: the work between rays (sampling, clustering, compression,
    /// allocation), from this technique's measured bakes.
    pub time_per_ray_time: f64,
    /// Occlusion rays per second the technique measured on a sample of its
    /// own occlusion rays, where it can make them without baking; the
    /// scene's generic rate otherwise.
    pub occlusion_rate: Option<f64>,
    /// Seconds the bake spends in work that does not grow with its rays.
    pub fixed_seconds: f64,
    /// The most bytes the bake holds at once on top of the loaded scene,
    /// with what holds them, largest first.
    pub peak: Vec<(String, u64)>,
    /// The parameters that lower the peak, as the user sets them, for the
    /// message that refuses a bake over the memory limit.
    pub lower_memory_with: String,
}

impl BakeEstimate {
    pub fn peak_bytes(&self) -> u64 {
        self.peak.iter().map(|(_, bytes)| bytes).sum()
    }

    /// Seconds the bake should take where the scene traces closest-hit and
    /// occlusion rays at these rates (rays per second).
    pub fn seconds(&self, closest_hit_rate: f64, occlusion_rate: f64) -> f64 {
        let ray_seconds = self.rays.closest_hit as f64 / closest_hit_rate.max(1.0)
            + self.rays.occlusion as f64 / self.occlusion_rate.unwrap_or(occlusion_rate).max(1.0);
        ray_seconds * self.time_per_ray_time + self.fixed_seconds
    }
}

/// Bytes this process holds in memory now (its resident set), where the
/// system tells it (Linux); `None` elsewhere.
pub fn resident_bytes() -> Option<u64> {
    kib_field(
        &std::fs::read_to_string("/proc/self/status").ok()?,
        "VmRSS:",
    )
}

/// A `Name:   1234 kB` line's value in bytes.
fn kib_field(text: &str, name: &str) -> Option<u64> {
    text.lines().find_map(|line| {
        let rest = line.strip_prefix(name)?;
        let kib: u64 = rest.trim().trim_end_matches("kB").trim().parse().ok()?;
        Some(kib * 1024)
    })
}

/// Memory a new allocation can have without swapping or being killed: the
/// kernel's available memory, lowered to what is left under this process's
/// control-group limit (containers, Kubernetes pods, Slurm jobs) when that
/// is less. `None` where neither is known.
pub fn available_bytes() -> Option<u64> {
    let available = std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|text| kib_field(&text, "MemAvailable:"));
    let group_left = cgroup_bytes_left();
    match (available, group_left) {
        (Some(a), Some(g)) => Some(a.min(g)),
        (a, g) => a.or(g),
    }
}

/// What is left under the cgroup v2 memory limit of this process.
fn cgroup_bytes_left() -> Option<u64> {
    let membership = std::fs::read_to_string("/proc/self/cgroup").ok()?;
    let path = membership
        .lines()
        .find_map(|line| line.strip_prefix("0::"))?
        .trim();
    let folder = std::path::Path::new("/sys/fs/cgroup").join(path.trim_start_matches('/'));
    let read = |name: &str| -> Option<u64> {
        std::fs::read_to_string(folder.join(name))
            .ok()?
            .trim()
            .parse()
            .ok()
    };
    // "max" (no limit) does not parse: no bound from the group.
    let limit = read("memory.max")?;
    let current = read("memory.current").unwrap_or(0);
    Some(limit.saturating_sub(current))
}

/// Parses a memory size as a user writes it: `4G`, `4GiB`, `512M`,
/// `512MB`, `1.5g`, or plain bytes. Units are binary (K = 1024 bytes), as
/// the peaks relight reports are.
pub fn parse_size(text: &str) -> Result<u64, String> {
    let trimmed = text.trim();
    let split = trimmed
        .find(|c: char| !(c.is_ascii_digit() || c == '.'))
        .unwrap_or(trimmed.len());
    let (number, unit) = trimmed.split_at(split);
    let value: f64 = number
        .parse()
        .map_err(|_| format!("'{text}' is not a size: write a number and a unit, as 4G or 512M"))?;
    let scale: u64 = match unit.trim().to_ascii_lowercase().as_str() {
        "" | "b" => 1,
        "k" | "kb" | "kib" => 1 << 10,
        "m" | "mb" | "mib" => 1 << 20,
        "g" | "gb" | "gib" => 1 << 30,
        "t" | "tb" | "tib" => 1 << 40,
        other => {
            return Err(format!(
                "'{text}': unknown unit '{other}'; use K, M, G or T (binary: 1K = 1024 bytes)"
            ))
        }
    };
    let bytes = value * scale as f64;
    if !bytes.is_finite() || bytes < 1.0 || bytes > u64::MAX as f64 {
        return Err(format!("'{text}' is not a usable memory size"));
    }
    Ok(bytes as u64)
}

/// `bytes` in MiB or GiB for messages.
pub fn format_bytes(bytes: u64) -> String {
    let mib = bytes as f64 / (1u64 << 20) as f64;
    if mib >= 10240.0 {
        format!("{:.1} GiB", mib / 1024.0)
    } else {
        format!("{mib:.0} MiB")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_parse_in_binary_units() {
        assert_eq!(parse_size("4G"), Ok(4 << 30));
        assert_eq!(parse_size("4GiB"), Ok(4 << 30));
        assert_eq!(parse_size("512mb"), Ok(512 << 20));
        assert_eq!(parse_size("1.5g"), Ok(3 << 29));
        assert_eq!(parse_size("1000"), Ok(1000));
        assert!(parse_size("lots").is_err());
        assert!(parse_size("4X").unwrap_err().contains("unit 'x'"));
        assert!(parse_size("0").is_err());
        assert!(parse_size("").is_err());
    }

    #[test]
    fn this_process_reports_its_memory_on_linux() {
        if cfg!(target_os = "linux") {
            let resident = resident_bytes().expect("statm on Linux");
            // A test binary's resident set is at least its code's pages and
            // far below the machine's memory.
            assert!(resident > 1 << 20, "{resident}");
            let available = available_bytes().expect("meminfo on Linux");
            assert!(available > 1 << 20, "{available}");
        }
    }

    #[test]
    fn estimates_turn_rays_into_seconds() {
        let estimate = BakeEstimate {
            rays: RayCount {
                closest_hit: 2_000_000,
                occlusion: 6_000_000,
            },
            time_per_ray_time: 1.5,
            occlusion_rate: None,
            fixed_seconds: 0.5,
            peak: vec![("panes".into(), 300), ("scratch".into(), 20)],
            lower_memory_with: String::new(),
        };
        // (2 M / 1 M/s + 6 M / 3 M/s) x 1.5 + 0.5 = 6.5 s.
        assert!((estimate.seconds(1e6, 3e6) - 6.5).abs() < 1e-9);
        assert_eq!(estimate.peak_bytes(), 320);
    }
}
