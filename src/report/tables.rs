//! The report's tables, each rendered both as Markdown (rounded, best value
//! in bold) and as CSV (full precision, no markup). Rows come only from the
//! records given, except the cost table, which also lists the paper's three
//! configurations (computed counts, not runs).

use super::RunRecord;
use crate::deform::count::{macs_per_gaussian, param_count, MacConvention};
use crate::deform::{Activation, FieldConfig, FieldKind, Variant};
use crate::error::Result;
use std::collections::BTreeMap;

/// One table cell.
#[derive(Clone, Debug, PartialEq)]
pub struct Cell {
    /// As shown in Markdown (rounded).
    pub md: String,
    /// As written to CSV (full precision; empty when missing).
    pub csv: String,
    /// Shown in bold in Markdown (the best value of its column).
    pub bold: bool,
}

impl Cell {
    fn new(md: String, csv: String) -> Self {
        Cell {
            md,
            csv,
            bold: false,
        }
    }
    /// A text cell, the same in Markdown and CSV.
    pub fn text(s: impl Into<String>) -> Self {
        let s = s.into();
        Cell::new(s.clone(), s)
    }
    /// A number shown with `decimals` places; the CSV keeps every digit.
    pub fn num(v: f64, decimals: usize) -> Self {
        Cell::new(format!("{v:.decimals$}"), v.to_string())
    }
    /// A number shown with `digits` significant digits in scientific notation.
    pub fn sci(v: f64, digits: usize) -> Self {
        let d = digits.saturating_sub(1);
        Cell::new(format!("{v:.d$e}"), v.to_string())
    }
    /// An integer shown with thousands separators.
    pub fn count(v: u64) -> Self {
        Cell::new(thousands(v), v.to_string())
    }
    /// A missing value: a dash in Markdown, empty in CSV.
    pub fn missing() -> Self {
        Cell::new("–".into(), String::new())
    }
}

/// `1234567` → `1,234,567`.
pub fn thousands(v: u64) -> String {
    let s = v.to_string();
    let mut out = String::new();
    for (i, c) in s.chars().enumerate() {
        if i > 0 && (s.len() - i).is_multiple_of(3) {
            out.push(',');
        }
        out.push(c);
    }
    out
}

/// A table: the first `left` columns are labels (left-aligned), the rest numbers.
#[derive(Clone, Debug, PartialEq)]
pub struct Table {
    /// Column headers.
    pub headers: Vec<String>,
    /// Number of leading label columns.
    pub left: usize,
    /// The rows, one cell per header.
    pub rows: Vec<Vec<Cell>>,
}

/// Which end of a column is best.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Better {
    /// Higher values are better (PSNR, SSIM).
    Higher,
    /// Lower values are better (LPIPS, time, smoothness).
    Lower,
}

impl Table {
    /// The table in Markdown, best values in bold.
    pub fn to_markdown(&self) -> String {
        let mut s = format!("| {} |\n|", self.headers.join(" | "));
        for i in 0..self.headers.len() {
            s += if i < self.left { "---|" } else { "---:|" };
        }
        s.push('\n');
        for row in &self.rows {
            let cells: Vec<String> = row
                .iter()
                .map(|c| match c.bold {
                    true => format!("**{}**", c.md),
                    false => c.md.clone(),
                })
                .collect();
            s += &format!("| {} |\n", cells.join(" | "));
        }
        s
    }

    /// The table as CSV at full precision, no markup.
    pub fn to_csv(&self) -> String {
        let mut s = csv_line(self.headers.iter().map(String::as_str));
        for row in &self.rows {
            s += &csv_line(row.iter().map(|c| c.csv.as_str()));
        }
        s
    }

    /// Bold the best value(s) of column `col`, compared as displayed (ties all bold).
    fn bold_best(&mut self, col: usize, better: Better) {
        let vals: Vec<Option<f64>> = self
            .rows
            .iter()
            .map(|r| r[col].md.parse::<f64>().ok())
            .collect();
        let best = vals.iter().flatten().copied().reduce(|a, b| match better {
            Better::Higher => a.max(b),
            Better::Lower => a.min(b),
        });
        if let (Some(best), true) = (best, self.rows.len() > 1) {
            for (row, v) in self.rows.iter_mut().zip(vals) {
                row[col].bold = v == Some(best);
            }
        }
    }
}

/// One CSV line (RFC 4180 quoting where needed).
pub fn csv_line<'a>(fields: impl Iterator<Item = &'a str>) -> String {
    let quoted: Vec<String> = fields
        .map(|f| {
            if f.contains([',', '"', '\n']) {
                format!("\"{}\"", f.replace('"', "\"\""))
            } else {
                f.to_string()
            }
        })
        .collect();
    quoted.join(",") + "\n"
}

/// A per-run quantity shown in a scene-by-row matrix.
pub struct Metric {
    /// The column header.
    pub name: &'static str,
    /// The metric's value in a record, when it has one.
    pub get: fn(&RunRecord) -> Option<f64>,
    /// How a value is shown.
    pub cell: fn(f64) -> Cell,
    /// Which end is best.
    pub better: Better,
}

/// Final test PSNR (dB).
pub const PSNR: Metric = Metric {
    name: "PSNR",
    get: |r| Some(r.test_psnr),
    cell: |v| Cell::num(v, 2),
    better: Better::Higher,
};
/// Final test SSIM.
pub const SSIM: Metric = Metric {
    name: "SSIM",
    get: |r| Some(r.test_ssim),
    cell: |v| Cell::num(v, 4),
    better: Better::Higher,
};
/// Final test LPIPS (with weights only).
pub const LPIPS: Metric = Metric {
    name: "LPIPS",
    get: |r| r.test_lpips,
    cell: |v| Cell::num(v, 4),
    better: Better::Lower,
};
/// Best periodic test PSNR (dB).
pub const BEST_PSNR: Metric = Metric {
    name: "best PSNR",
    get: |r| r.best.as_ref().map(|b| b.psnr.value),
    cell: |v| Cell::num(v, 2),
    better: Better::Higher,
};
/// Best periodic test SSIM.
pub const BEST_SSIM: Metric = Metric {
    name: "best SSIM",
    get: |r| r.best.as_ref().and_then(|b| b.ssim).map(|b| b.value),
    cell: |v| Cell::num(v, 4),
    better: Better::Higher,
};
/// Best periodic test LPIPS.
pub const BEST_LPIPS: Metric = Metric {
    name: "best LPIPS",
    get: |r| r.best.as_ref().and_then(|b| b.lpips).map(|b| b.value),
    cell: |v| Cell::num(v, 4),
    better: Better::Lower,
};
/// Mean wall-clock milliseconds per training iteration.
pub const MS_PER_ITER: Metric = Metric {
    name: "ms/iter",
    get: |r| Some(r.ms_per_iteration),
    cell: |v| Cell::num(v, 1),
    better: Better::Lower,
};
/// Temporal smoothness of the learned deformation (lower is smoother).
pub const SMOOTHNESS: Metric = Metric {
    name: "smoothness",
    get: |r| r.temporal_smoothness,
    cell: |v| Cell::sci(v, 4),
    better: Better::Lower,
};

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len() as f64
}

/// Rows (label, runs) × columns (scene × metric), then the mean over the
/// scenes every row has (header says how many when not all). Several seeds of
/// one (row, scene) are averaged; the `seeds` column lists them. Rows with no
/// value for any metric are dropped. Returns `None` when no row remains.
pub fn matrix(
    row_header: &str,
    groups: &[(String, Vec<&RunRecord>)],
    metrics: &[Metric],
) -> Option<Table> {
    let mut scenes: Vec<&str> = groups
        .iter()
        .flat_map(|g| g.1.iter().map(|r| r.scene.as_str()))
        .collect();
    scenes.sort();
    scenes.dedup();
    // value[row][scene][metric]
    let mut value: Vec<Vec<Vec<Option<f64>>>> = Vec::new();
    let mut kept: Vec<&(String, Vec<&RunRecord>)> = Vec::new();
    for g in groups {
        let v: Vec<Vec<Option<f64>>> = scenes
            .iter()
            .map(|s| {
                metrics
                    .iter()
                    .map(|m| {
                        let xs: Vec<f64> =
                            g.1.iter()
                                .filter(|r| r.scene == *s)
                                .filter_map(|r| (m.get)(r))
                                .collect();
                        (!xs.is_empty()).then(|| mean(&xs))
                    })
                    .collect()
            })
            .collect();
        if v.iter().flatten().any(Option::is_some) {
            value.push(v);
            kept.push(g);
        }
    }
    if kept.is_empty() {
        return None;
    }
    let common: Vec<usize> = (0..scenes.len())
        .filter(|&s| value.iter().all(|row| row[s].iter().all(Option::is_some)))
        .collect();
    let with_mean = scenes.len() > 1 && !common.is_empty();
    let mut headers = vec![row_header.to_string(), "params".into(), "seeds".into()];
    for s in &scenes {
        headers.extend(metrics.iter().map(|m| format!("{s} {}", m.name)));
    }
    if with_mean {
        let which = if common.len() == scenes.len() {
            String::new()
        } else {
            format!(" ({} of {} scenes)", common.len(), scenes.len())
        };
        headers.extend(metrics.iter().map(|m| format!("mean {}{which}", m.name)));
    }
    let mut t = Table {
        headers,
        left: 3,
        rows: Vec::new(),
    };
    for (g, v) in kept.iter().zip(&value) {
        let mut seeds: Vec<u64> = g.1.iter().map(|r| r.seed).collect();
        seeds.sort();
        seeds.dedup();
        let seeds: Vec<String> = seeds.iter().map(u64::to_string).collect();
        let mut row = vec![
            Cell::text(&g.0),
            Cell::count(g.1[0].params as u64),
            Cell::text(seeds.join(" ")),
        ];
        for per_scene in v {
            for (m, x) in metrics.iter().zip(per_scene) {
                row.push(x.map_or_else(Cell::missing, m.cell));
            }
        }
        if with_mean {
            for (i, m) in metrics.iter().enumerate() {
                let xs: Vec<f64> = common
                    .iter()
                    .map(|&s| v[s][i].unwrap_or(f64::NAN))
                    .collect();
                row.push((m.cell)(mean(&xs)));
            }
        }
        t.rows.push(row);
    }
    for c in t.left..t.headers.len() {
        t.bold_best(c, metrics[(c - t.left) % metrics.len()].better);
    }
    Some(t)
}

/// One row per run: the final model's metrics and the best of the periodic
/// evaluations with the iteration each came from. `None` without records.
pub fn final_and_best(records: &[RunRecord]) -> Option<Table> {
    if records.is_empty() {
        return None;
    }
    let lpips = records.iter().any(|r| r.test_lpips.is_some());
    let mut headers: Vec<String> = [
        "scene",
        "field",
        "seed",
        "evaluations",
        "final PSNR",
        "final SSIM",
    ]
    .map(String::from)
    .to_vec();
    if lpips {
        headers.push("final LPIPS".into());
    }
    headers.extend(["best PSNR (iteration)", "best SSIM (iteration)"].map(String::from));
    if lpips {
        headers.push("best LPIPS (iteration)".into());
    }
    let mut runs: Vec<&RunRecord> = records.iter().collect();
    runs.sort_by(|a, b| {
        (a.scene.as_str(), field_order(a), a.seed).cmp(&(b.scene.as_str(), field_order(b), b.seed))
    });
    let with_it = |b: Option<super::BestValue>, decimals: usize| -> Cell {
        b.map_or_else(Cell::missing, |b| {
            Cell::text(format!(
                "{:.*} ({})",
                decimals,
                b.value,
                thousands(b.iteration as u64)
            ))
        })
    };
    let rows = runs
        .iter()
        .map(|r| {
            let b = r.best.as_ref();
            let mut row = vec![
                Cell::text(&r.scene),
                Cell::text(&r.field),
                Cell::text(r.seed.to_string()),
                b.map_or_else(Cell::missing, |b| Cell::count(b.evaluations as u64)),
                Cell::num(r.test_psnr, 2),
                Cell::num(r.test_ssim, 4),
            ];
            if lpips {
                row.push(r.test_lpips.map_or_else(Cell::missing, |v| Cell::num(v, 4)));
            }
            row.push(with_it(b.map(|b| b.psnr), 2));
            row.push(with_it(b.and_then(|b| b.ssim), 4));
            if lpips {
                row.push(with_it(b.and_then(|b| b.lpips), 4));
            }
            row
        })
        .collect();
    Some(Table {
        headers,
        left: 3,
        rows,
    })
}

/// Group records by a key, in key order.
pub fn group_by<K: Ord>(
    records: &[RunRecord],
    key: impl Fn(&RunRecord) -> Option<(K, String)>,
) -> Vec<(String, Vec<&RunRecord>)> {
    let mut map: BTreeMap<K, (String, Vec<&RunRecord>)> = BTreeMap::new();
    for r in records {
        if let Some((k, label)) = key(r) {
            map.entry(k)
                .or_insert_with(|| (label, Vec::new()))
                .1
                .push(r);
        }
    }
    map.into_values().collect()
}

/// Sort key of a field configuration: MLP first, then depth, width, activation.
pub fn field_order(r: &RunRecord) -> (bool, usize, usize, String, String) {
    (
        r.kind != "mlp",
        r.depth,
        r.width,
        r.activation.clone(),
        r.field.clone(),
    )
}

/// Groups by field label (one row per field configuration).
pub fn by_field(records: &[RunRecord]) -> Vec<(String, Vec<&RunRecord>)> {
    group_by(records, |r| Some((field_order(r), r.field.clone())))
}

/// The configuration the ablations vary one setting of.
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct AblationBase {
    /// CfC cells of the base configuration.
    pub depth: usize,
    /// CfC hidden size of the base configuration.
    pub width: usize,
    /// Backbone activation of the base configuration.
    pub activation: String,
}

impl Default for AblationBase {
    /// The paper's CfC default: D6, W128, GELU.
    fn default() -> Self {
        AblationBase {
            depth: 6,
            width: 128,
            activation: "gelu".into(),
        }
    }
}

/// Depth ablation (CfC runs at the base width and activation), one row per depth.
pub fn depth_ablation(records: &[RunRecord], base: &AblationBase) -> Option<Table> {
    let g = group_by(records, |r| {
        (r.kind == "cfc" && r.width == base.width && r.activation == base.activation)
            .then(|| (r.depth, format!("D={}", r.depth)))
    });
    matrix("depth", &g, &[PSNR, SSIM])
}

/// Activation ablation (CfC runs at the base depth and width), in the paper's order.
pub fn activation_ablation(records: &[RunRecord], base: &AblationBase) -> Option<Table> {
    const ORDER: [&str; 5] = ["gelu", "relu", "silu", "lecun_tanh", "tanh"];
    let g = group_by(records, |r| {
        let pos = ORDER
            .iter()
            .position(|a| *a == r.activation)
            .unwrap_or(ORDER.len());
        (r.kind == "cfc" && r.depth == base.depth && r.width == base.width)
            .then(|| ((pos, r.activation.clone()), r.activation.clone()))
    });
    matrix("activation", &g, &[PSNR, SSIM])
}

/// Per-stage mean milliseconds per iteration, one row per run, when any run recorded stages.
pub fn stage_table(records: &[RunRecord]) -> Option<Table> {
    let mut stages: Vec<&String> = records.iter().flat_map(|r| r.stage_ms.keys()).collect();
    stages.sort();
    stages.dedup();
    if stages.is_empty() {
        return None;
    }
    let mut headers = vec![
        "scene".to_string(),
        "field".into(),
        "seed".into(),
        "threads".into(),
    ];
    headers.extend(stages.iter().map(|s| format!("{s} ms")));
    headers.push("total ms".into());
    let mut runs: Vec<&RunRecord> = records.iter().filter(|r| !r.stage_ms.is_empty()).collect();
    runs.sort_by_key(|r| (r.scene.clone(), field_order(r), r.seed));
    let rows = runs
        .iter()
        .map(|r| {
            let mut row = vec![
                Cell::text(&r.scene),
                Cell::text(&r.field),
                Cell::text(r.seed.to_string()),
                Cell::text(r.threads.to_string()),
            ];
            row.extend(stages.iter().map(|s| {
                r.stage_ms
                    .get(*s)
                    .map_or_else(Cell::missing, |v| Cell::num(*v, 1))
            }));
            row.push(Cell::num(r.ms_per_iteration, 1));
            row
        })
        .collect();
    Some(Table {
        headers,
        left: 4,
        rows,
    })
}

/// The paper's Table 3 configurations: (kind, depth, width, activation).
pub const PAPER_CONFIGS: [(FieldKind, usize, usize, Activation); 3] = [
    (FieldKind::Mlp, 8, 256, Activation::Relu),
    (FieldKind::Cfc, 8, 256, Activation::Gelu),
    (FieldKind::Cfc, 6, 128, Activation::Gelu),
];

/// Parameters and MACs per Gaussian of the paper's configurations (synthetic
/// input) and of every configuration that was run, under each ptflops
/// convention (see [`crate::deform::count`]).
pub fn cost_table(records: &[RunRecord]) -> Result<Table> {
    let mut configs: Vec<(FieldConfig, bool, bool)> = Vec::new(); // (config, paper, run here)
    for (kind, depth, width, activation) in PAPER_CONFIGS {
        let c = FieldConfig::sized(kind, Variant::Synthetic, depth, width, activation)?;
        configs.push((c, true, false));
    }
    let mut run_configs: Vec<FieldConfig> = Vec::new();
    for r in records {
        let c = r.field_config()?;
        if !run_configs.contains(&c) {
            run_configs.push(c);
        }
    }
    run_configs.sort_by_key(|c| {
        let names = (c.activation().name(), c.variant().name());
        (c.kind() != FieldKind::Mlp, c.depth(), c.width(), names)
    });
    for c in run_configs {
        match configs.iter_mut().find(|x| x.0 == c) {
            Some(x) => x.2 = true,
            None => configs.push((c, false, true)),
        }
    }
    let mut headers = vec![
        "field".to_string(),
        "input".into(),
        "source".into(),
        "params".into(),
    ];
    headers.extend(["MACs aten", "MACs pytorch", "MACs pytorch no-functional"].map(String::from));
    let mut rows = Vec::new();
    for (c, paper, run) in configs {
        let act = c.activation().name();
        let source = match (paper, run) {
            (true, true) => "paper config, run here",
            (true, false) => "paper config, not run",
            _ => "run here",
        };
        let mut row = vec![
            Cell::text(format!("{}-d{}-w{}-{act}", c.kind(), c.depth(), c.width())),
            Cell::text(if c.variant() == Variant::Synthetic {
                "synthetic (timenet)"
            } else {
                "real (γ10(t))"
            }),
            Cell::text(source),
            Cell::count(param_count(&c)? as u64),
        ];
        for conv in MacConvention::ALL {
            row.push(Cell::count(macs_per_gaussian(&c, conv)?));
        }
        rows.push(row);
    }
    Ok(Table {
        headers,
        left: 3,
        rows,
    })
}

#[cfg(test)]
mod tests {
    use super::super::tests::record;
    use super::*;

    #[test]
    fn quality_table_markdown_snapshot() {
        let recs = vec![
            record("lego", "mlp", 8, 256, "relu", 0, 31.5, 0.95),
            record("lego", "cfc", 6, 128, "gelu", 0, 32.3, 0.951),
            record("jumpingjacks", "mlp", 8, 256, "relu", 0, 30.0, 0.96),
            record("jumpingjacks", "cfc", 6, 128, "gelu", 0, 29.0, 0.96),
        ];
        let t = matrix("field", &by_field(&recs), &[PSNR, SSIM]).unwrap();
        // Means: mlp (30 + 31.5)/2 = 30.75, (0.96 + 0.95)/2 = 0.955;
        // cfc (29 + 32.3)/2 = 30.65, (0.96 + 0.951)/2 = 0.9555.
        let expect = "\
| field | params | seeds | jumpingjacks PSNR | jumpingjacks SSIM | lego PSNR | lego SSIM | mean PSNR | mean SSIM |
|---|---|---|---:|---:|---:|---:|---:|---:|
| mlp-d8-w256-relu | 522,280 | 0 | **30.00** | **0.9600** | 31.50 | 0.9500 | **30.75** | 0.9550 |
| cfc-d6-w128-gelu | 334,504 | 0 | 29.00 | **0.9600** | **32.30** | **0.9510** | 30.65 | **0.9555** |
";
        assert_eq!(t.to_markdown(), expect);
    }

    #[test]
    fn missing_cells_and_partial_means() {
        let recs = vec![
            record("a", "cfc", 6, 128, "gelu", 0, 20.0, 0.5),
            record("a", "cfc", 8, 128, "gelu", 0, 21.0, 0.6),
            record("b", "cfc", 6, 128, "gelu", 0, 22.0, 0.7),
            record("a", "cfc", 6, 128, "relu", 0, 99.0, 0.9), // not in the depth ablation
        ];
        let t = depth_ablation(&recs, &AblationBase::default()).unwrap();
        assert_eq!(t.headers[7], "mean PSNR (1 of 2 scenes)");
        assert_eq!(t.rows[0][0].md, "D=6");
        assert_eq!(t.rows[1][5].md, "–");
        assert_eq!(t.rows[1][7].md, "21.00");
        assert!(t.rows[1][7].bold && !t.rows[0][7].bold);
        let a = activation_ablation(&recs, &AblationBase::default()).unwrap();
        let names: Vec<&str> = a.rows.iter().map(|r| r[0].md.as_str()).collect();
        assert_eq!(names, ["gelu", "relu"]);
        assert!(matrix("field", &by_field(&recs), &[SMOOTHNESS]).is_none());
    }

    #[test]
    fn cost_table_lists_paper_configs_and_runs() {
        let recs = vec![
            record("a", "cfc", 10, 128, "tanh", 0, 20.0, 0.5),
            record("a", "cfc", 6, 128, "gelu", 0, 20.0, 0.5),
        ];
        let t = cost_table(&recs).unwrap();
        let col = |i: usize, c: usize| t.rows[i][c].csv.clone();
        // docs/UPSTREAM.md §8.2/§8.3: 522,280 / 782,888 / 334,504 parameters; aten MACs
        // equal them.
        assert_eq!(
            (col(0, 3), col(1, 3), col(2, 3)),
            ("522280".into(), "782888".into(), "334504".into())
        );
        assert_eq!(
            (col(0, 4), col(2, 5), col(2, 6)),
            ("522280".into(), "336552".into(), "335528".into())
        );
        assert_eq!(col(2, 2), "paper config, run here");
        assert_eq!(
            (col(3, 0), col(3, 2)),
            ("cfc-d10-w128-tanh".into(), "run here".into())
        );
        assert_eq!(t.rows.len(), 4);
    }

    #[test]
    fn csv_quotes_and_thousands() {
        assert_eq!(
            csv_line(["a", "b,c", "d\"e"].into_iter()),
            "a,\"b,c\",\"d\"\"e\"\n"
        );
        assert_eq!(thousands(0), "0");
        assert_eq!(thousands(1000), "1,000");
        assert_eq!(thousands(334504), "334,504");
    }
}
