//! Pipeline loading against a small catalog that mimics the real one.

use crate::catalog::*;
use crate::checks::*;
use crate::params::*;
use crate::pipeline::*;
use crate::{load_str, LoadError};
use serde::{Deserialize, Serialize};
use std::path::Path;

#[derive(Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields, default)]
struct ProjectParams {
    min_depth: f32,
    border: u32,
}

impl Validate for ProjectParams {
    fn validate(&self) -> Vec<ParamProblem> {
        ParamChecks::new().within("min_depth", self.min_depth as f64, 0.0, 1000.0).done()
    }
}

/// Params with every kind of range check, for the diagnostics they give.
#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
struct RangeParams {
    lo: f64,
    hi: f64,
    size: u32,
    names: Vec<String>,
}

impl Default for RangeParams {
    fn default() -> Self {
        RangeParams { lo: 0.0, hi: 1.0, size: 4, names: vec!["a".into()] }
    }
}

impl Validate for RangeParams {
    fn validate(&self) -> Vec<ParamProblem> {
        ParamChecks::new()
            .within("lo", self.lo, -10.0, 10.0)
            .within("hi", self.hi, -10.0, 10.0)
            .below("lo", self.lo, "hi", self.hi)
            .count("size", self.size as u64, 1, 64)
            .path_names("names", &self.names)
            .done()
    }
}

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
struct DataConfig {
    root: String,
    version: String,
}

impl Default for DataConfig {
    fn default() -> Self {
        DataConfig { root: String::new(), version: "v1.0-mini".into() }
    }
}

impl Validate for DataConfig {}

#[derive(Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct NoParams {}

impl Validate for NoParams {}

const DIMS: [DimSpec; 3] = [
    DimSpec { name: "scene", ordered: false },
    DimSpec { name: "frame", ordered: true },
    DimSpec { name: "camera", ordered: false },
];
const PORTS: [SourcePortSpec; 2] = [
    SourcePortSpec { name: "lidar", ty: "PointCloud", grain: "frame", doc: "" },
    SourcePortSpec { name: "image", ty: "Image", grain: "camera", doc: "" },
];

struct Cat {
    stages: Vec<StageSchema>,
    data: DatasetSchema,
}

impl Catalog for Cat {
    fn stage(&self, kind: &str) -> Option<&StageSchema> {
        self.stages.iter().find(|s| s.kind == kind)
    }
    fn stage_kinds(&self) -> Vec<&'static str> {
        self.stages.iter().map(|s| s.kind).collect()
    }
    fn dataset(&self, kind: &str) -> Option<&DatasetSchema> {
        (kind == self.data.kind).then_some(&self.data)
    }
    fn dataset_kinds(&self) -> Vec<&'static str> {
        vec![self.data.kind]
    }
    fn exportable(&self, ty: &str) -> bool {
        ty == "File"
    }
}

fn stage(
    kind: &'static str,
    inputs: Vec<PortSpec>,
    outputs: Vec<PortSpec>,
    grains: Vec<&'static str>,
    params: ParamsSpec,
) -> StageSchema {
    StageSchema {
        kind,
        version: 1,
        summary: "",
        inputs,
        outputs,
        grains,
        params,
        seeded: false,
        export_template_params: vec![],
        aligned_inputs: vec![],
        variants: None,
        unused_inputs: None,
    }
}

fn catalog() -> Cat {
    Cat {
        stages: vec![
            stage(
                "Project",
                vec![PortSpec::one("points", "PointCloud", ""), PortSpec::one("image", "Image", "")],
                vec![PortSpec::one("depth", "DepthMap", "")],
                vec!["camera"],
                ParamsSpec::of::<ProjectParams>(),
            ),
            stage(
                "Encode",
                vec![PortSpec::one("depth", "DepthMap", "")],
                vec![PortSpec::one("png", "File", ""), PortSpec::one("depth", "DepthMap", "")],
                vec!["camera", "frame"],
                ParamsSpec::of::<NoParams>(),
            ),
            stage(
                "Fuse",
                vec![PortSpec::many("depths", "DepthMap", "")],
                vec![PortSpec::one("depth", "DepthMap", "")],
                vec!["frame", "camera"],
                ParamsSpec::of::<NoParams>(),
            ),
            stage(
                "Range",
                vec![],
                vec![PortSpec::one("depth", "DepthMap", "")],
                vec!["camera"],
                ParamsSpec::of::<RangeParams>(),
            ),
        ],
        data: DatasetSchema {
            kind: "NuScenes",
            summary: "",
            dims: DIMS.to_vec(),
            ports: PORTS.to_vec(),
            config: ParamsSpec::of::<DataConfig>(),
            path_fields: vec!["root"],
        },
    }
}

fn load(text: &str, sets: &[&str]) -> Result<Pipeline, LoadError> {
    let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
    load_str("p.ron", text, Path::new("dir/p.ron"), Path::new("/base"), &sets, Path::new("/cwd"), &catalog())
}

const GOOD: &str = r#"Pipeline(
    dataset: NuScenes(root: "data"),
    stages: {
        "project": Project(
            inputs: {"points": "dataset.lidar", "image": "dataset.image"},
            params: (min_depth: 1.0),
        ),
        "encode": Encode(inputs: {"depth": "project.depth"}),
        "fuse": Fuse(inputs: {"depths": Gather("project.depth", camera)}),
        "window": Fuse(inputs: {"depths": Window("fuse.depth", frame, -1, 1)}),
    },
    export: {"encode.png": "{scene}/{camera}/{frame}.png"},
)"#;

fn errors(text: &str, sets: &[&str]) -> String {
    load(text, sets).map(|_| "loaded".to_string()).unwrap_or_else(|e| e.render())
}

#[test]
fn a_good_pipeline_loads_into_a_typed_dag() {
    let p = load(GOOD, &[]).unwrap();
    assert_eq!(p.name, "p");
    assert_eq!(p.dataset.config.canonical, r#"(root:"/base/data",version:"v1.0-mini")"#);
    let project = &p.nodes[p.node_by_name("project").unwrap()];
    assert_eq!(project.grain, 3);
    assert_eq!(project.stage().unwrap().params.canonical, "(min_depth:1.0,border:0)");
    let fuse = &p.nodes[p.node_by_name("fuse").unwrap()];
    assert_eq!(fuse.grain, 2);
    assert_eq!(fuse.stage().unwrap().inputs[0].selector, Selector::Gather { dim: 2 });
    let window = p.nodes[p.node_by_name("window").unwrap()].stage().unwrap();
    assert_eq!(window.inputs[0].selector, Selector::Window { dim: 1, before: -1, after: 1 });
    // Sources come before the stages that read them.
    let pos = |n: &str| p.order.iter().position(|&i| p.nodes[i].name == n).unwrap();
    assert!(pos("dataset.lidar") < pos("project") && pos("project") < pos("fuse") && pos("fuse") < pos("window"));
    assert_eq!(p.exports.len(), 1);
    assert!(p.to_dot().contains("Gather(camera)"));
}

#[test]
fn set_overrides_params_and_dataset_fields() {
    let p = load(GOOD, &["project.min_depth=2.5", "dataset.root=rel/x", "dataset.version=v1.0-trainval"]).unwrap();
    let project = &p.nodes[p.node_by_name("project").unwrap()];
    assert_eq!(project.stage().unwrap().params.canonical, "(min_depth:2.5,border:0)");
    assert_eq!(p.dataset.config.canonical, r#"(root:"/cwd/rel/x",version:"v1.0-trainval")"#);
}

#[test]
fn set_replaces_the_whole_dataset_and_refuses_what_is_not_one() {
    // Fields of the new dataset are checked and its relative paths are the working directory's.
    let p = load(GOOD, &["dataset=NuScenes(root: \"other\", version: \"v1.0-test\")"]).unwrap();
    assert_eq!(p.dataset.config.canonical, r#"(root:"/cwd/other",version:"v1.0-test")"#);
    // A field set beside it applies to the new dataset, whatever the order.
    let p = load(GOOD, &["dataset.version=v1.0-trainval", "dataset=NuScenes(root: \"other\")"]).unwrap();
    assert_eq!(p.dataset.config.canonical, r#"(root:"/cwd/other",version:"v1.0-trainval")"#);
    let out = errors(GOOD, &["dataset=NuScenes(rot: \"x\")", "dataset=[1]"]);
    assert!(out.contains("unknown param `rot` of dataset NuScenes") && out.contains("--> --set:1:18"), "{out}");
    assert!(out.contains("takes a dataset, like") && out.contains("--> --set:1:9"), "{out}");
}

#[test]
fn set_dataset_keeps_the_fields_the_new_kind_shares_but_not_its_paths() {
    // video_12hz.ron's `frames: Camera` must survive `--set 'dataset=Py123d(root: ..)'`.
    let pipeline = GOOD.replace(r#"NuScenes(root: "data")"#, r#"NuScenes(root: "data", version: "v1.0-test")"#);
    let p = load(&pipeline, &["dataset=NuScenes(root: \"other\")"]).unwrap();
    assert_eq!(p.dataset.config.canonical, r#"(root:"/cwd/other",version:"v1.0-test")"#);
    // What the replacement sets wins; a root left out is the new kind's default, not the old root.
    let p = load(&pipeline, &["dataset=NuScenes(version: \"v1.0-mini\")"]).unwrap();
    assert!(!p.dataset.config.canonical.contains("data"), "{}", p.dataset.config.canonical);
    assert!(p.dataset.config.canonical.contains(r#"version:"v1.0-mini""#), "{}", p.dataset.config.canonical);
}

#[test]
fn set_errors_point_into_the_argument() {
    let out = errors(GOOD, &["project.min_dept=2", "nosuch.x=1", "project.border=-1"]);
    assert!(out.contains("unknown param `min_dept`"), "{out}");
    assert!(out.contains("--> --set:1:9"), "{out}");
    assert!(out.contains("did you mean `min_depth`?"), "{out}");
    assert!(out.contains("stage `nosuch`, which the pipeline does not have"), "{out}");
}

#[test]
fn every_problem_is_reported_at_once_with_locations() {
    let text = r#"Pipeline(
    dataset: NuScenes(root: "data", versoin: "x"),
    stages: {
        "project": Project(
            inputs: {"points": "dataset.image", "imag": "dataset.image"},
            params: (min_dept: 1.0, border: 2),
        ),
        "encode": Encdoe(inputs: {"depth": "project.depth"}),
        "fuse": Fuse(inputs: {"depths": "project.depht"}),
    },
)"#;
    let out = errors(text, &[]);
    // Dataset config.
    assert!(out.contains("unknown param `versoin` of dataset NuScenes"), "{out}");
    assert!(out.contains("p.ron:2:37"), "{out}");
    // Unknown kind, with a suggestion and the list.
    assert!(out.contains("unknown stage kind `Encdoe`"), "{out}");
    assert!(out.contains("did you mean `Encode`?"), "{out}");
    // Unknown param, naming what exists.
    assert!(out.contains("unknown param `min_dept`"), "{out}");
    assert!(out.contains("params: min_depth (default 0.0), border (default 0)"), "{out}");
    // Type mismatch names both types.
    assert!(
        out.contains("input `points` of stage `project` takes PointCloud but `dataset.image` gives Image"),
        "{out}"
    );
    // Unknown input port and the missing one.
    assert!(out.contains("has no input port `imag`"), "{out}");
    assert!(out.contains("input `image` (Image) of stage `project` is not wired"), "{out}");
    // Unknown output port with suggestion.
    assert!(out.contains("stage `project` has no output port `depht`"), "{out}");
    // Carets under the offending text.
    assert!(
        out.contains("            params: (min_dept: 1.0, border: 2),\n  |                      ^^^^^^^^"),
        "{out}"
    );
    assert!(out.contains("problems found; nothing was run"), "{out}");
}

#[test]
fn syntax_errors_have_a_location() {
    let out = errors("Pipeline(\n  dataset: NuScenes(root: \"x\")\n  stages: {},\n)", &[]);
    assert!(out.contains("expected `,` or `)`"), "{out}");
    assert!(out.contains("p.ron:3:3"), "{out}");
}

#[test]
fn type_errors_in_params_point_at_the_value() {
    let text = GOOD.replace("min_depth: 1.0", "min_depth: \"far\"");
    let out = errors(&text, &[]);
    assert!(out.contains("bad params of stage `project` (Project): expected a number, found a string"), "{out}");
    assert!(out.contains("p.ron:6:33"), "{out}");
}

#[test]
fn cycles_name_their_stages() {
    let text = r#"Pipeline(
    dataset: NuScenes(root: "d"),
    stages: {
        "a": Fuse(inputs: {"depths": Window("c.depth", frame, -1, 0)}),
        "b": Fuse(inputs: {"depths": "a.depth"}),
        "c": Fuse(inputs: {"depths": "b.depth"}),
        "ok": Fuse(inputs: {"depths": "c.depth"}),
    },
)"#;
    let out = errors(text, &[]);
    assert!(out.contains("the stages `a` -> `b` -> `c` form a cycle"), "{out}");
    assert!(!out.contains("`ok`"), "{out}");
}

#[test]
fn all_reads_every_upstream_item_under_the_outer_item() {
    let text = GOOD.replace(
        r#""window": Fuse("#,
        r#""all": Fuse(inputs: {"depths": All("project.depth")}, grain: frame),
        "window": Fuse("#,
    );
    let p = load(&text, &[]).unwrap();
    let all = p.nodes[p.node_by_name("all").unwrap()].stage().unwrap();
    assert_eq!(all.inputs[0].selector, Selector::All);
    assert!(p.to_dot().contains("depth -> depths All"), "{}", p.to_dot());
    // The selector names no dimension; the usage note speaks the dataset's own dimension names.
    let out = errors(&text.replace("All(", "Scene("), &[]);
    assert!(out.contains("unknown selector `Scene`"), "{out}");
    assert!(out.contains(r#"Window("stage.port", frame, -1, 1)"#), "{out}");
    assert!(
        out.contains(r#"Gather("stage.port", camera), Across("stage.port", camera) or All("stage.port")"#),
        "{out}"
    );
}

#[test]
fn selectors_must_fit_the_grains() {
    let text = r#"Pipeline(
    dataset: NuScenes(root: "d"),
    stages: {
        "project": Project(inputs: {"points": "dataset.lidar", "image": "dataset.image"}),
        "fine_to_coarse": Fuse(inputs: {"depths": "project.depth"}),
        "gather_wrong": Fuse(inputs: {"depths": Gather("project.depth", frame)}),
        "window_camera": Fuse(inputs: {"depths": Window("project.depth", camera, -1, 1)}),
        "one_gets_many": Encode(inputs: {"depth": Window("project.depth", frame, -1, 1)}),
        "unknown_dim": Fuse(inputs: {"depths": Offset("project.depth", time, 1)}),
        "bad_grain": Project(inputs: {"points": "dataset.lidar", "image": "dataset.image"}, grain: frame),
    },
)"#;
    let out = errors(text, &[]);
    assert!(out.contains("stage `fine_to_coarse` runs per frame but its input `depths` from `project.depth` (per camera) is finer: gather it with Gather(\"..\", camera)"), "{out}");
    assert!(out.contains("cannot be gathered over `frame`"), "{out}");
    assert!(out.contains("`Window` cannot move along `camera`: it has no order"), "{out}");
    assert!(
        out.contains(
            "input `depth` of stage `one_gets_many` takes one DepthMap but Window(frame, -1, 1) gives several"
        ),
        "{out}"
    );
    assert!(out.contains("the dataset has no dimension `time`"), "{out}");
    assert!(out.contains("stage `bad_grain` (Project) cannot run per `frame`"), "{out}");
}

/// An exported stage whose grain is refused used to crash the check (the export template was read
/// against grain 0); the grain is reported and the export left unchecked.
#[test]
fn an_exported_stage_with_a_bad_grain_is_a_diagnostic() {
    for grain in ["scene", "nosuch", "42"] {
        let text = GOOD.replace(
            r#""encode": Encode(inputs: {"depth": "project.depth"}),"#,
            &format!(r#""encode": Encode(inputs: {{"depth": "project.depth"}}, grain: {grain}),"#),
        );
        let out = errors(&text, &[]);
        assert!(out.contains("stage `encode` (Encode) cannot run per"), "{grain}: {out}");
        assert!(out.contains("1 problem found"), "{grain}: {out}");
    }
}

#[test]
fn exports_need_files_and_every_dimension_of_the_grain() {
    let text = GOOD.replace(
        r#"export: {"encode.png": "{scene}/{camera}/{frame}.png"}"#,
        r#"export: {"encode.png": "{scene}/{frame}.png", "encode.depth": "{scene}/{frame}/{camera}.bin", "nope.x": "a"}"#,
    );
    let out = errors(&text, &[]);
    assert!(out.contains("it must name `{camera}`"), "{out}");
    assert!(out.contains("`encode.depth` gives DepthMap, which is not an encoded file"), "{out}");
    assert!(out.contains("export names stage `nope`"), "{out}");
}

#[test]
fn a_dimension_may_be_named_by_its_token_or_zero_padded_and_nothing_else() {
    let text = GOOD.replace(
        r#"export: {"encode.png": "{scene}/{camera}/{frame}.png"}"#,
        r#"export: {"encode.png": "{scene}/{frame.token}/{camera}.png"}"#,
    );
    let p = load(&text, &[]).unwrap();
    assert!(p.exports[0].parts.contains(&TemplatePart::Token(1)), "{:?}", p.exports[0].parts);
    let bad = text.replace("{frame.token}", "{frame.name}");
    let out = errors(&bad, &[]);
    assert!(out.contains("unknown field `.name` in `{frame.name}`"), "{out}");
    let padded = load(&text.replace("{frame.token}", "{frame:06}"), &[]).unwrap();
    assert!(padded.exports[0].parts.contains(&TemplatePart::Padded(1, 6)), "{:?}", padded.exports[0].parts);
    let out = errors(&text.replace("{frame.token}", "{frame:6}"), &[]);
    assert!(out.contains("the format is `:0N`"), "{out}");
}

#[test]
fn every_takes_a_positive_whole_number() {
    let with = |every: &str| GOOD.replacen("\"fuse\": Fuse(", &format!("\"fuse\": Fuse(every: {every}, "), 1);
    assert!(with("2").contains("every: 2"), "{}", with("2"));
    let p = load(&with("2"), &[]).unwrap();
    assert_eq!(p.nodes[p.node_by_name("fuse").unwrap()].stage().unwrap().every, 2);
    let out = errors(&with("0"), &[]);
    assert!(out.contains("`every` is a whole number of items, 1 to 1000000, found 0"), "{out}");
}

#[test]
fn missing_dataset_and_unknown_top_level_fields() {
    let out = errors("Pipeline(stages: {}, stagse: 1)", &[]);
    assert!(out.contains("the pipeline has no `dataset`"), "{out}");
    assert!(out.contains("unknown field `stagse` in Pipeline"), "{out}");
    assert!(out.contains("did you mean `stages`?"), "{out}");
}

/// GOOD with a `Range` stage whose params are `params`.
fn with_range(params: &str) -> String {
    GOOD.replace(
        "        \"encode\": Encode(",
        &format!("        \"r\": Range(\n            params: {params},\n        ),\n        \"encode\": Encode("),
    )
}

#[test]
fn params_out_of_range_are_reported_at_the_written_value() {
    let text = with_range(r#"(lo: 5, hi: 2, size: 0, names: ["a", "../b", "a", ""])"#);
    let out = errors(&text, &[]);
    // Line 9 is the params line; columns count from 1.
    let line = text.lines().nth(8).unwrap();
    let col = |needle: &str| line.find(needle).unwrap() + 1;
    assert!(out.contains("`size` of stage `r` (Range) must be in 1..=64, found 0"), "{out}");
    assert!(out.contains(&format!("p.ron:9:{}", col("0,"))), "{out}");
    assert!(out.contains("`lo` of stage `r` (Range) must be below `hi` (2), found 5"), "{out}");
    assert!(out.contains(&format!("p.ron:9:{}", col("5,"))), "{out}");
    // List elements are pointed at one by one.
    assert!(
        out.contains("`names` of stage `r` (Range) must be one file or folder name, without `/`, found `../b`"),
        "{out}"
    );
    assert!(out.contains(&format!("p.ron:9:{}", col("\"../b\""))), "{out}");
    assert!(out.contains("`names` of stage `r` (Range) names `a` twice"), "{out}");
    assert!(out.contains(&format!("p.ron:9:{}", col("\"a\", \"\""))), "{out}");
    assert!(out.contains("must not be empty"), "{out}");
    assert!(out.contains("5 problems found"), "{out}");
    // NaN and infinities are not numbers in range.
    let out = errors(&with_range("(hi: NaN, lo: -inf)"), &[]);
    assert!(out.contains("`hi` of stage `r` (Range) must be a number in [-10, 10], found NaN"), "{out}");
    assert!(out.contains("`lo` of stage `r` (Range) must be a number in [-10, 10], found -inf"), "{out}");
}

#[test]
fn a_relation_broken_by_one_written_param_points_at_it() {
    // `lo` keeps its default 0 and `hi` is written: the diagnostic is at `hi`, naming `lo`'s default.
    let text = with_range("(hi: -1)");
    let out = errors(&text, &[]);
    assert!(out.contains("`lo` of stage `r` (Range) must be below `hi` (-1), found 0"), "{out}");
    let line = text.lines().nth(8).unwrap();
    assert!(out.contains(&format!("p.ron:9:{}", line.find("-1").unwrap() + 1)), "{out}");
    assert!(out.contains("`lo` is not written here, so it has its default 0.0"), "{out}");
}

#[test]
fn params_out_of_range_through_set_point_into_the_argument() {
    let out = errors(GOOD, &["project.min_depth=-1", "project.border=3"]);
    assert!(out.contains("`min_depth` of stage `project` (Project) must be a number in [0, 1000], found -1"), "{out}");
    assert!(out.contains("--> --set:1:19"), "{out}");
    assert!(out.contains("1 problem found"), "{out}");
    // A stage written without params gets them from --set, and their problems point there too.
    let out = errors(&with_range("()"), &["r.size=65"]);
    assert!(out.contains("`size` of stage `r` (Range) must be in 1..=64, found 65"), "{out}");
    assert!(out.contains("--> --set:1:8"), "{out}");
}

#[test]
fn values_nested_too_deep_are_refused_at_their_position() {
    use crate::syntax::MAX_NESTING;
    // Far beyond the limit (this overflowed the stack) and one level beyond it.
    for depth in [20_000, MAX_NESTING] {
        let text = format!("Pipeline(name: {}{})", "[".repeat(depth), "]".repeat(depth));
        let out = errors(&text, &[]);
        assert!(out.contains(&format!("values nest deeper than {MAX_NESTING} levels here")), "{out}");
        // `Pipeline(` is level 1, so the first refused `[` is number MAX_NESTING.
        assert!(out.contains(&format!("p.ron:1:{}", "Pipeline(name: ".len() + MAX_NESTING)), "{out}");
    }
    // Through --set: an error at the argument, not a plain string, not a crash.
    let deep = format!("project.min_depth={}", "[".repeat(20_000));
    let out = errors(GOOD, &[&deep]);
    assert!(out.contains("values nest deeper than"), "{out}");
    assert!(out.contains(&format!("--> --set:1:{}", "project.min_depth=".len() + MAX_NESTING + 1)), "{out}");
    // At the limit, values still parse.
    let mut sources = crate::source::Sources::default();
    let id = sources.add("t", "");
    let at_limit = format!("{}{}", "[".repeat(MAX_NESTING), "]".repeat(MAX_NESTING));
    assert!(crate::syntax::parse(&at_limit, id).is_ok());
    let over = format!("[{at_limit}]");
    let e = crate::syntax::parse_value(&over, id).unwrap_err();
    assert!(e.too_deep && e.diagnostic.span.unwrap().start as usize == MAX_NESTING, "{e:?}");
}

#[test]
fn selector_offsets_out_of_range_are_refused_even_the_most_negative() {
    for (offset, ok) in [
        ("-9223372036854775808", false),
        ("9223372036854775807", false),
        ("1000000", false),
        ("-1000000", false),
        ("999999", true),
        ("-999999", true),
    ] {
        let text = GOOD.replace(
            r#""window": Fuse(inputs: {"depths": Window("fuse.depth", frame, -1, 1)}),"#,
            &format!(r#""window": Fuse(inputs: {{"depths": Offset("fuse.depth", frame, {offset})}}),"#),
        );
        let out = errors(&text, &[]);
        if ok {
            assert_eq!(out, "loaded", "{offset}");
        } else {
            assert!(out.contains(&format!("the offset {offset} is out of range: offsets are within ±999999")), "{out}");
            assert!(out.contains("p.ron:10:71"), "{out}");
        }
    }
}

#[test]
fn a_file_that_is_not_utf8_is_refused_at_its_first_bad_byte() {
    let dir = std::env::temp_dir().join(format!("dist4d-graph-utf8-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("bad.ron");
    // Line 2, after `  name: "ça` (11 characters, 12 bytes): byte 10 + 12 = 22, column 12.
    std::fs::write(&file, b"Pipeline(\n  name: \"\xc3\xa7a\xff\",\n)\n").unwrap();
    let e = crate::load_file(&file, &[], &dir, &catalog()).unwrap_err();
    let out = e.render();
    std::fs::remove_dir_all(&dir).unwrap();
    assert!(
        out.contains("the pipeline file is not valid UTF-8: byte 22 (0xFF) is not part of a valid character"),
        "{out}"
    );
    assert!(out.contains("bad.ron:2:12"), "{out}");
}
