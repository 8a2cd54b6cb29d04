//! Structure-aware mutation of the files users edit or exchange (the
//! scanner geometry's TOML, the calibration's and the scan manifest's JSON,
//! a material file's safetensors header and metadata).
//!
//! libFuzzer's byte mutations rarely keep such a file parseable and almost
//! never write what breaks a reader that parses it: a count of 10¹⁵, a
//! NaN, a list repeated forty times, a key removed. [`mutate`] parses the
//! input as a document, changes one to four of its nodes by kind (a number
//! to an edge of a range or a power of ten, an array's element repeated or
//! dropped, a key removed or renamed, a subtree copied over another) and
//! writes it again. A seeded generator makes every choice, so libFuzzer's
//! seed and the input reproduce the mutation. An input that does not parse
//! takes a document seen before ([`with_pool`]); one mutation in four is
//! libFuzzer's own, so that syntax errors are still explored.

/// The syntax of a document.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Syntax {
    Json,
    Toml,
}

/// One node of a JSON or TOML document. Integers are wider than either
/// format's so that mutations can write values beyond `u64` (a JSON reader
/// then reads a float or refuses them); floats may be NaN or infinite
/// (TOML writes them; JSON gets `1e999`, which readers refuse or read as
/// infinite).
#[derive(Clone, Debug, PartialEq)]
pub enum Node {
    Null,
    Bool(bool),
    Int(i128),
    Float(f64),
    Str(String),
    Arr(Vec<Node>),
    Map(Vec<(String, Node)>),
}

/// Integers at the edges of the ranges that counts, indices, sizes and
/// times take.
const INTS: &[i128] = &[
    0,
    1,
    -1,
    2,
    3,
    7,
    8,
    15,
    16,
    63,
    64,
    65,
    127,
    128,
    255,
    256,
    1023,
    1024,
    4095,
    4096,
    65_535,
    65_536,
    1_000_000,
    (1 << 31) - 1,
    1 << 31,
    (1 << 32) - 1,
    1 << 32,
    1 << 53,
    1_000_000_000_000_000,
    i64::MAX as i128,
    i64::MIN as i128,
    u64::MAX as i128,
    (u64::MAX as i128) + 1,
];

/// Floats at the edges: the specials, the extremes, the subnormals.
const FLOATS: &[f64] = &[
    0.0,
    -0.0,
    0.5,
    -1.0,
    1e-9,
    1e9,
    1e15,
    1e300,
    -1e300,
    f64::MAX,
    f64::MIN_POSITIVE,
    5e-324,
    f64::NAN,
    f64::INFINITY,
    f64::NEG_INFINITY,
];

/// Strings a reader may take for a name, a path, a hash or a number.
const STRS: &[&str] = &[
    "",
    "0",
    "-1",
    "NaN",
    "1e999",
    "x",
    "é\u{0}\u{202e}",
    "../../../../etc/passwd",
    "/dev/zero",
    "manifest.json",
    "frame-00.exr",
    "0000000000000000000000000000000000000000000000000000000000000000",
];

/// A small seeded generator (SplitMix64).
#[derive(Clone, Debug)]
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Self {
        Rng(seed)
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in `0..n` (`n` > 0).
    pub fn below(&mut self, n: usize) -> usize {
        (self.next_u64() % n as u64) as usize
    }

    fn pick<'a, T>(&mut self, items: &'a [T]) -> &'a T {
        &items[self.below(items.len())]
    }
}

/// Parses a document; `None` if it is not one.
pub fn parse(text: &[u8], syntax: Syntax) -> Option<Node> {
    let text = std::str::from_utf8(text).ok()?;
    match syntax {
        Syntax::Json => serde_json::from_str::<serde_json::Value>(text).ok().map(from_json),
        Syntax::Toml => {
            toml::from_str::<toml::Table>(text).ok().map(|t| from_toml(toml::Value::Table(t)))
        }
    }
}

fn from_json(v: serde_json::Value) -> Node {
    use serde_json::Value as V;
    match v {
        V::Null => Node::Null,
        V::Bool(b) => Node::Bool(b),
        V::Number(n) => match (n.as_i64(), n.as_u64()) {
            (Some(i), _) => Node::Int(i.into()),
            (_, Some(u)) => Node::Int(u.into()),
            _ => Node::Float(n.as_f64().unwrap_or(f64::NAN)),
        },
        V::String(s) => Node::Str(s),
        V::Array(a) => Node::Arr(a.into_iter().map(from_json).collect()),
        V::Object(m) => Node::Map(m.into_iter().map(|(k, v)| (k, from_json(v))).collect()),
    }
}

fn from_toml(v: toml::Value) -> Node {
    use toml::Value as V;
    match v {
        V::Boolean(b) => Node::Bool(b),
        V::Integer(i) => Node::Int(i.into()),
        V::Float(f) => Node::Float(f),
        V::String(s) => Node::Str(s),
        V::Datetime(d) => Node::Str(d.to_string()),
        V::Array(a) => Node::Arr(a.into_iter().map(from_toml).collect()),
        V::Table(t) => Node::Map(t.into_iter().map(|(k, v)| (k, from_toml(v))).collect()),
    }
}

/// Writes a document; `None` if TOML cannot hold it (a root that is not a
/// table).
pub fn write(node: &Node, syntax: Syntax) -> Option<Vec<u8>> {
    match syntax {
        Syntax::Json => {
            let mut out = String::new();
            write_json(node, &mut out);
            Some(out.into_bytes())
        }
        Syntax::Toml => match to_toml(node)? {
            toml::Value::Table(t) => toml::to_string(&t).ok().map(String::into_bytes),
            _ => None,
        },
    }
}

fn write_json(node: &Node, out: &mut String) {
    use std::fmt::Write;
    match node {
        Node::Null => out.push_str("null"),
        Node::Bool(b) => write!(out, "{b}").unwrap(),
        Node::Int(i) => write!(out, "{i}").unwrap(),
        Node::Float(f) if f.is_nan() => out.push_str("NaN"),
        Node::Float(f) if f.is_infinite() => {
            out.push_str(if *f > 0.0 { "1e999" } else { "-1e999" })
        }
        // `{:?}` keeps the exponent and a fraction, so it reads back a float.
        Node::Float(f) => write!(out, "{f:?}").unwrap(),
        Node::Str(s) => out.push_str(&serde_json::Value::String(s.clone()).to_string()),
        Node::Arr(a) => {
            out.push('[');
            for (i, n) in a.iter().enumerate() {
                if i > 0 {
                    out.push(',');
                }
                write_json(n, out);
            }
            out.push(']');
        }
        Node::Map(m) => {
            out.push('{');
            for (i, (k, n)) in m.iter().enumerate() {
                if i > 0 {
                    out.push(',');
                }
                out.push_str(&serde_json::Value::String(k.clone()).to_string());
                out.push(':');
                write_json(n, out);
            }
            out.push('}');
        }
    }
}

/// TOML has no null (a null member is left out) and 64-bit integers (a
/// wider one becomes the nearest float).
fn to_toml(node: &Node) -> Option<toml::Value> {
    use toml::Value as V;
    Some(match node {
        Node::Null => return None,
        Node::Bool(b) => V::Boolean(*b),
        Node::Int(i) => i64::try_from(*i).map(V::Integer).unwrap_or(V::Float(*i as f64)),
        Node::Float(f) => V::Float(*f),
        Node::Str(s) => V::String(s.clone()),
        Node::Arr(a) => V::Array(a.iter().filter_map(to_toml).collect()),
        Node::Map(m) => {
            V::Table(m.iter().filter_map(|(k, n)| Some((k.clone(), to_toml(n)?))).collect())
        }
    })
}

/// The paths (child indices from the root) of every node, the root first.
fn paths(node: &Node, prefix: &mut Vec<usize>, out: &mut Vec<Vec<usize>>) {
    out.push(prefix.clone());
    let children: Box<dyn Iterator<Item = &Node>> = match node {
        Node::Arr(a) => Box::new(a.iter()),
        Node::Map(m) => Box::new(m.iter().map(|(_, n)| n)),
        _ => return,
    };
    for (i, c) in children.enumerate() {
        prefix.push(i);
        paths(c, prefix, out);
        prefix.pop();
    }
}

fn at<'a>(node: &'a mut Node, path: &[usize]) -> &'a mut Node {
    path.iter().fold(node, |n, &i| match n {
        Node::Arr(a) => &mut a[i],
        Node::Map(m) => &mut m[i].1,
        _ => unreachable!("a path only goes through arrays and maps"),
    })
}

/// A scalar of any kind, at an edge.
fn scalar(rng: &mut Rng) -> Node {
    match rng.below(6) {
        0 => Node::Null,
        1 => Node::Bool(rng.below(2) == 1),
        2 => Node::Int(*rng.pick(INTS)),
        3 => Node::Float(*rng.pick(FLOATS)),
        4 => Node::Str(rng.pick(STRS).to_string()),
        _ => [Node::Arr(Vec::new()), Node::Map(Vec::new())][rng.below(2)].clone(),
    }
}

/// Changes one node of `doc`: by its kind most of the time, else replaces
/// it with a scalar or a copy of another node. An array's repeated element
/// adds at most about `max_bytes` to the document.
pub fn mutate_once(doc: &mut Node, rng: &mut Rng, max_bytes: usize) {
    let mut all = Vec::new();
    paths(doc, &mut Vec::new(), &mut all);
    let path = rng.pick(&all).clone();
    let donor = at(doc, rng.pick(&all)).clone();
    let node = at(doc, &path);
    match rng.below(8) {
        0 => *node = scalar(rng),
        // A subtree copied over another: a table's rows in the wrong place,
        // a list where a number was.
        1 if !path.is_empty() => *node = donor,
        _ => match node {
            Node::Int(i) => {
                *i = match rng.below(4) {
                    0 => *rng.pick(INTS),
                    1 => i.saturating_add(if rng.below(2) == 0 { 1 } else { -1 }),
                    2 => i.saturating_neg(),
                    _ => i.saturating_mul(10i128.pow(1 + rng.below(15) as u32)),
                }
            }
            Node::Float(f) => {
                *f = match rng.below(4) {
                    0 => *rng.pick(FLOATS),
                    1 => -*f,
                    2 => *f * 10f64.powi(rng.below(41) as i32 - 20),
                    _ => f.round(),
                }
            }
            Node::Bool(b) => *b = !*b,
            Node::Str(s) => match rng.below(3) {
                0 => *s = rng.pick(STRS).to_string(),
                1 => s.truncate(
                    s.char_indices().nth(rng.below(s.len() + 1)).map_or(s.len(), |c| c.0),
                ),
                _ => s.push_str(&s.clone()),
            },
            Node::Arr(a) if !a.is_empty() => {
                let i = rng.below(a.len());
                match rng.below(5) {
                    0 => {
                        a.remove(i);
                    }
                    1 => a.truncate(i),
                    2 => {
                        let j = rng.below(a.len());
                        a.swap(i, j)
                    }
                    // An element repeated: a frame listed twice, a mirror
                    // more than the scanner has.
                    _ => {
                        let e = a[i].clone();
                        let mut text = String::new();
                        write_json(&e, &mut text);
                        let copies = [1, 2, 40, 64, 1000][rng.below(5)];
                        let copies = copies.min(max_bytes / (text.len() + 1));
                        a.splice(i..i, std::iter::repeat_n(e, copies));
                    }
                }
            }
            Node::Map(m) if !m.is_empty() => {
                let i = rng.below(m.len());
                match rng.below(3) {
                    0 => {
                        m.remove(i);
                    }
                    // A key misspelt, or duplicated (JSON keeps both).
                    1 => m[i].0.push('_'),
                    _ => {
                        let e = m[i].clone();
                        m.insert(i, e);
                    }
                }
            }
            _ => *node = scalar(rng),
        },
    }
}

/// One to four mutations of the document in `data[..size]`, written back
/// into `data`. Returns the new size, or `None` if the input does not parse
/// or its mutation does not fit `max_size` (the target then uses
/// libFuzzer's own mutator).
pub fn mutate(
    data: &mut [u8],
    size: usize,
    max_size: usize,
    seed: u32,
    syntax: Syntax,
) -> Option<usize> {
    let mut rng = Rng::new(seed.into());
    let mut doc = parse(&data[..size], syntax)?;
    mutate_some(&mut doc, &mut rng, max_size);
    let out = write(&doc, syntax)?;
    put(data, max_size, &[&out])
}

/// [`mutate`] of a JSON document.
pub fn json_file(data: &mut [u8], size: usize, max_size: usize, seed: u32) -> Option<usize> {
    mutate(data, size, max_size, seed, Syntax::Json)
}

/// [`mutate`] of a TOML document.
pub fn toml_file(data: &mut [u8], size: usize, max_size: usize, seed: u32) -> Option<usize> {
    mutate(data, size, max_size, seed, Syntax::Toml)
}

/// Mutates a material file (docs/material-format.md): a safetensors file,
/// whose JSON header describes the tensors and whose `__metadata__`
/// entry `material` is a JSON document of its own (as a string). Two times
/// in three that inner document is mutated, else the header (a tensor's
/// dtype, shape or offsets); the tensor bytes are kept and the header's
/// length written anew.
pub fn material_file(data: &mut [u8], size: usize, max_size: usize, seed: u32) -> Option<usize> {
    let mut rng = Rng::new(seed.into());
    let bytes = &data[..size];
    let n = usize::try_from(u64::from_le_bytes(bytes.get(..8)?.try_into().ok()?)).ok()?;
    let mut header = parse(bytes.get(8..8usize.checked_add(n)?)?, Syntax::Json)?;
    let tensors = bytes[8 + n..].to_vec();
    let inner = member(member(&mut header, "__metadata__")?, "material")?;
    match inner {
        Node::Str(text) if rng.below(3) != 0 => {
            let mut doc = parse(text.as_bytes(), Syntax::Json)?;
            mutate_some(&mut doc, &mut rng, max_size);
            *text = String::from_utf8(write(&doc, Syntax::Json)?).ok()?;
        }
        _ => mutate_some(&mut header, &mut rng, max_size),
    }
    let head = write(&header, Syntax::Json)?;
    put(data, max_size, &[&(head.len() as u64).to_le_bytes(), &head, &tensors])
}

/// The most documents [`with_pool`] keeps.
const POOL: usize = 64;

/// `mutate` (one of the functions above) of the input, or, if it does not
/// parse, of a document seen before. The fuzzer's corpus fills with inputs
/// that do not parse (their parser's error paths are new coverage), and
/// without the pool most mutations would then be byte mutations: on a
/// calibration corpus of 7 000 inputs, 11 % of them were structured. Each
/// input that parses replaces one of the last 64 kept.
pub fn with_pool(
    mutate: fn(&mut [u8], usize, usize, u32) -> Option<usize>,
    data: &mut [u8],
    size: usize,
    max_size: usize,
    seed: u32,
) -> Option<usize> {
    static KEPT: std::sync::Mutex<Vec<Vec<u8>>> = std::sync::Mutex::new(Vec::new());
    let input = data[..size].to_vec();
    if let Some(n) = mutate(data, size, max_size, seed) {
        let mut kept = KEPT.lock().unwrap();
        if kept.len() < POOL {
            kept.push(input);
        } else {
            kept[seed as usize % POOL] = input;
        }
        return Some(n);
    }
    let doc = {
        let kept = KEPT.lock().unwrap();
        kept.get(seed as usize % kept.len().max(1))?.clone()
    };
    if doc.len() > max_size.min(data.len()) {
        return None;
    }
    data[..doc.len()].copy_from_slice(&doc);
    mutate(data, doc.len(), max_size, seed)
}

/// The member `key` of a map.
fn member<'a>(node: &'a mut Node, key: &str) -> Option<&'a mut Node> {
    match node {
        Node::Map(m) => m.iter_mut().find(|(k, _)| k == key).map(|(_, n)| n),
        _ => None,
    }
}

/// One to four mutations; a repeated list adds at most about a quarter of
/// `max_size` each.
fn mutate_some(doc: &mut Node, rng: &mut Rng, max_size: usize) {
    for _ in 0..1 + rng.below(4) {
        mutate_once(doc, rng, max_size / 4);
    }
}

/// Writes `parts` one after the other into `data`, if they fit `max_size`.
fn put(data: &mut [u8], max_size: usize, parts: &[&[u8]]) -> Option<usize> {
    let len: usize = parts.iter().map(|p| p.len()).sum();
    if len > max_size {
        return None;
    }
    let mut at = 0;
    for p in parts {
        data[at..at + p.len()].copy_from_slice(p);
        at += p.len();
    }
    Some(len)
}

#[cfg(test)]
mod tests {
    use super::*;

    const JSON: &str = r#"{"mirror_count": 3, "frames": [{"mirror": 0, "exposure_us": 50000, "sha256": "ab"},
        {"mirror": 1, "exposure_us": 50000.5, "sha256": "cd"}], "settings": {"hdr": true, "bracket_us": []}}"#;
    const TOML: &str = "name = \"x\"\n[camera]\nwidth = 4096\nfocal_mm = 35.0\n[[mirror]]\ncenter_mm = [1.0, 2.0, 3.5]\n[[mirror]]\ncenter_mm = [4.0, 5.0, 6.0]\n";

    #[test]
    fn a_document_reads_back_as_itself() {
        for (text, syntax) in [(JSON, Syntax::Json), (TOML, Syntax::Toml)] {
            let doc = parse(text.as_bytes(), syntax).unwrap();
            let again = parse(&write(&doc, syntax).unwrap(), syntax).unwrap();
            assert_eq!(doc, again, "{syntax:?}");
        }
    }

    #[test]
    fn mutations_parse_differ_and_reach_the_edges() {
        // Over many seeds: every JSON mutation of a JSON file is JSON again
        // (but for NaN and 1e999, which serde_json refuses), every TOML one
        // TOML; they change the document, and among them are the faults of
        // session 44: a count of 10¹⁵ or more, a NaN in the TOML, a list
        // repeated past 64 elements.
        let (mut huge_count, mut toml_nan, mut long_list, mut unchanged) = (false, false, false, 0);
        for seed in 0..5000u32 {
            for (text, syntax) in [(JSON, Syntax::Json), (TOML, Syntax::Toml)] {
                let mut data = text.as_bytes().to_vec();
                data.resize(1 << 16, 0);
                let Some(n) = mutate(&mut data, text.len(), 1 << 16, seed, syntax) else {
                    assert_eq!(syntax, Syntax::Toml, "seed {seed}: JSON always writes");
                    continue;
                };
                let out = std::str::from_utf8(&data[..n]).unwrap();
                let doc = parse(out.as_bytes(), syntax);
                if syntax == Syntax::Toml || !(out.contains("NaN") || out.contains("1e999")) {
                    assert!(doc.is_some(), "seed {seed}: {out}");
                }
                unchanged += usize::from(out == text);
                if let Some(Node::Map(m)) = &doc {
                    let count = m.iter().find(|(k, _)| k == "mirror_count");
                    huge_count |=
                        matches!(count, Some((_, Node::Int(i))) if *i >= 1_000_000_000_000_000);
                    let frames = m.iter().find(|(k, _)| k == "frames");
                    long_list |= matches!(frames, Some((_, Node::Arr(a))) if a.len() > 64);
                }
                toml_nan |= syntax == Syntax::Toml && out.contains("nan");
            }
        }
        assert!(huge_count && toml_nan && long_list, "{huge_count} {toml_nan} {long_list}");
        assert!(unchanged < 100, "{unchanged} of 10 000 mutations changed nothing");
    }

    #[test]
    fn a_seed_reproduces_its_mutation_and_the_size_is_kept() {
        let run = |seed, max| {
            let mut data = JSON.as_bytes().to_vec();
            data.resize(JSON.len().max(max), 0);
            mutate(&mut data, JSON.len(), max, seed, Syntax::Json).map(|n| data[..n].to_vec())
        };
        for seed in 0..200 {
            assert_eq!(run(seed, 4096), run(seed, 4096));
            if let Some(out) = run(seed, 200) {
                assert!(out.len() <= 200);
            }
        }
    }
    #[test]
    fn a_material_keeps_its_container_and_its_tensors() {
        // A safetensors file of one tensor whose metadata is a document.
        let meta = r#"{"resolution": 4, "lights": [{"mirror": 0, "direction": [0.0, 0.0, 1.0]}]}"#;
        let header = format!(
            r#"{{"__metadata__": {{"material": {}}}, "indices": {{"dtype": "U8", "shape": [2], "data_offsets": [0, 2]}}}}"#,
            serde_json::Value::String(meta.into())
        );
        let mut file = (header.len() as u64).to_le_bytes().to_vec();
        file.extend_from_slice(header.as_bytes());
        file.extend_from_slice(&[7, 9]);
        let (mut inner_changed, mut header_changed) = (0, 0);
        for seed in 0..2000u32 {
            let mut data = file.clone();
            data.resize(1 << 16, 0);
            let n = material_file(&mut data, file.len(), 1 << 16, seed).unwrap();
            let len = u64::from_le_bytes(data[..8].try_into().unwrap()) as usize;
            assert_eq!(&data[8 + len..n], &[7, 9], "seed {seed}: the tensor bytes");
            let head = std::str::from_utf8(&data[8..8 + len]).unwrap();
            let Some(Node::Map(h)) = parse(head.as_bytes(), Syntax::Json) else {
                // A header mutated into NaN, 1e999 or a scalar.
                assert!(!head.starts_with('{') || head.contains("NaN") || head.contains("1e999"));
                header_changed += 1;
                continue;
            };
            let text = |h: &[(String, Node)]| match h.iter().find(|(k, _)| k == "__metadata__") {
                Some((_, Node::Map(m))) => match m.iter().find(|(k, _)| k == "material") {
                    Some((_, Node::Str(s))) => Some(s.clone()),
                    _ => None,
                },
                _ => None,
            };
            match text(&h) {
                Some(t) if t != meta => inner_changed += 1,
                _ => header_changed += 1,
            }
        }
        // Two in three mutate the material's own document.
        assert!((1100..1550).contains(&inner_changed), "{inner_changed} {header_changed}");
    }
    #[test]
    fn an_input_that_does_not_parse_takes_a_document_seen_before() {
        let mut data = vec![0u8; 1 << 16];
        // Nothing seen yet: nothing to mutate.
        data[..5].copy_from_slice(b"{oops");
        assert_eq!(with_pool(json_file, &mut data, 5, 1 << 16, 1), None);
        data[..JSON.len()].copy_from_slice(JSON.as_bytes());
        assert!(with_pool(json_file, &mut data, JSON.len(), 1 << 16, 2).is_some());
        // Now an input that does not parse is replaced by a mutation of it.
        let mut parsed = 0;
        for seed in 0..200 {
            data[..5].copy_from_slice(b"{oops");
            let n = with_pool(json_file, &mut data, 5, 1 << 16, seed).unwrap();
            let out = std::str::from_utf8(&data[..n]).unwrap();
            assert!(!out.starts_with("{oops"), "seed {seed}");
            parsed += usize::from(parse(out.as_bytes(), Syntax::Json).is_some());
        }
        assert!(parsed > 150, "{parsed} of 200 parse");
    }
}
