//! Where a config's problems are: each as FILE:LINE:COL with its message ([`Problem`],
//! [`ConfigErrors`]), found by walking the TOML document's spans.

use super::*;

/// One problem in a config file, at a line and column (1-based) where one is known.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Problem {
    pub line: Option<usize>,
    pub column: Option<usize>,
    pub message: String,
}

/// Everything wrong with a config file. `Display` prints one problem per line,
/// `FILE:LINE:COL: message` (or `FILE: message` where there is no position).
#[derive(Debug)]
pub struct ConfigErrors {
    pub path: PathBuf,
    pub problems: Vec<Problem>,
}

impl ConfigErrors {
    /// A single problem without a position (e.g. the file cannot be read).
    pub fn single(path: &Path, message: impl Into<String>) -> ConfigErrors {
        ConfigErrors {
            path: path.to_path_buf(),
            problems: vec![Problem { line: None, column: None, message: message.into() }],
        }
    }
}

impl fmt::Display for ConfigErrors {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, p) in self.problems.iter().enumerate() {
            if i > 0 {
                writeln!(f)?;
            }
            match (p.line, p.column) {
                (Some(l), Some(c)) => write!(f, "{}:{l}:{c}: {}", self.path.display(), p.message)?,
                (Some(l), None) => write!(f, "{}:{l}: {}", self.path.display(), p.message)?,
                _ => write!(f, "{}: {}", self.path.display(), p.message)?,
            }
        }
        Ok(())
    }
}

impl std::error::Error for ConfigErrors {}

/// The 1-based line and column (in characters) of a byte offset of `text`.
pub fn line_column(text: &str, offset: usize) -> (usize, usize) {
    let mut offset = offset.min(text.len());
    while !text.is_char_boundary(offset) {
        offset -= 1;
    }
    let before = &text[..offset];
    let line = before.matches('\n').count() + 1;
    let line_start = before.rfind('\n').map_or(0, |i| i + 1);
    (line, text[line_start..offset].chars().count() + 1)
}

/// One step of a path into the TOML document: a key or an array index.
#[derive(Clone, Copy, Debug)]
pub(crate) enum Seg<'s> {
    K(&'s str),
    I(usize),
}

/// The parsed document with its spans, to place problems found after parsing.
pub(crate) struct Doc<'a> {
    pub(crate) text: &'a str,
    pub(crate) root: Spanned<DeTable<'a>>,
    pub(crate) problems: Vec<(Option<Range<usize>>, String)>,
}

impl<'a> Doc<'a> {
    /// The span of the value at `path`, or of the nearest enclosing value that exists (a table's
    /// span is its header).
    pub(crate) fn span(&self, path: &[Seg]) -> Option<Range<usize>> {
        let mut best = None;
        let mut table: Option<&DeTable> = Some(self.root.get_ref());
        let mut value: Option<&Spanned<DeValue>> = None;
        for seg in path {
            let next = match (seg, table, value) {
                (Seg::K(k), Some(t), _) => t.iter().find(|(key, _)| key.get_ref() == k).map(|(_, v)| v),
                (Seg::I(i), _, Some(v)) => v.get_ref().as_array().and_then(|a| a.get(*i)),
                _ => None,
            };
            let Some(next) = next else { break };
            best = Some(next.span());
            value = Some(next);
            table = next.get_ref().as_table();
        }
        best
    }

    pub(crate) fn at(&mut self, path: &[Seg], message: impl Into<String>) {
        let span = self.span(path);
        self.problems.push((span, message.into()));
    }

    pub(crate) fn at_span(&mut self, span: Option<Range<usize>>, message: impl Into<String>) {
        self.problems.push((span, message.into()));
    }

    /// A problem with something the file lacks: at `path` where it is there but empty (`nodes =
    /// []`), else at the file's last line, where it would go.
    pub(crate) fn at_missing(&mut self, path: &[Seg], message: impl Into<String>) {
        let end = self.text.trim_end().len();
        let line_start = self.text[..end].rfind('\n').map_or(0, |i| i + 1);
        let span = self.span(path).unwrap_or(line_start..line_start);
        self.problems.push((Some(span), message.into()));
    }

    /// The line of the value at `path`, for messages that refer to another place.
    pub(crate) fn line_of(&self, path: &[Seg]) -> Option<usize> {
        self.span(path).map(|s| line_column(self.text, s.start).0)
    }

    pub(crate) fn value(&self, key: &str) -> Option<&Spanned<DeValue<'a>>> {
        self.root.get_ref().iter().find(|(k, _)| k.get_ref() == key).map(|(_, v)| v)
    }

    /// Deserializes one value, recording its errors with their positions. Deserializing stops at
    /// a table's first error, so a table is read again without the entry at fault until it reads
    /// or an error belongs to no entry: every problem of the table is recorded, not only the first.
    /// The value is returned where only unknown keys were left out (the table's own rules can then
    /// be checked too); an entry whose value was refused leaves `None`.
    pub(crate) fn de<T: for<'de> Deserialize<'de>>(&mut self, value: &Spanned<DeValue<'a>>) -> Option<T> {
        let mut value = value.clone();
        let mut left_out: Vec<String> = Vec::new();
        let mut values_left_out = false;
        loop {
            let e = match T::deserialize(ValueDeserializer::from(value.clone())) {
                Ok(t) => return (!values_left_out).then_some(t),
                Err(e) => e,
            };
            let message = e.message().to_string();
            // A required key whose value was refused: reported already.
            if left_out.iter().any(|k| message.starts_with(&format!("missing field `{k}`"))) {
                return None;
            }
            let span = e.span().unwrap_or_else(|| value.span());
            self.at_span(Some(span.clone()), message.clone());
            let DeValue::Table(table) = value.get_mut() else { return None };
            let within = |r: Range<usize>| r.contains(&span.start) || (r.is_empty() && r.start == span.start);
            let key = table
                .iter()
                .find(|(k, v)| within(k.span()) || within(v.span()))
                .map(|(k, _)| k.get_ref().to_string())?;
            values_left_out |= !message.starts_with("unknown field");
            table.remove(key.as_str());
            left_out.push(key);
        }
    }

    pub(crate) fn into_errors(self, path: &Path) -> ConfigErrors {
        let text = self.text;
        let mut problems: Vec<Problem> = self
            .problems
            .into_iter()
            .map(|(span, message)| {
                let pos = span.map(|s| line_column(text, s.start));
                Problem { line: pos.map(|p| p.0), column: pos.map(|p| p.1), message }
            })
            .collect();
        // In file order, problems without a position last (a stable sort keeps equal positions
        // in the order found).
        problems.sort_by_key(|p| (p.line.is_none(), p.line, p.column));
        ConfigErrors { path: path.to_path_buf(), problems }
    }
}

pub(crate) fn doc_value<'a>(doc: &Doc<'a>, key: &str) -> Option<Spanned<DeValue<'a>>> {
    doc.value(key).cloned()
}

/// The items of `[[tiles]]` or `[[nodes]]` that parsed (with their index), and the names of those
/// that did not (so references to them are not reported twice).
pub(crate) struct Parsed<T> {
    pub(crate) items: Vec<(usize, T)>,
    pub(crate) failed_names: Vec<String>,
    pub(crate) any_failed: bool,
    pub(crate) present: bool,
}

pub(crate) fn doc_list<T: for<'de> Deserialize<'de>>(doc: &mut Doc<'_>, key: &str) -> Parsed<T> {
    let mut out = Parsed { items: Vec::new(), failed_names: Vec::new(), any_failed: false, present: false };
    let Some(value) = doc.value(key).cloned() else { return out };
    out.present = true;
    let Some(array) = value.get_ref().as_array() else {
        // Not an array: let serde say so.
        let _: Option<Vec<T>> = doc.de(&value);
        out.any_failed = true;
        return out;
    };
    for (i, item) in array.iter().enumerate() {
        match doc.de::<T>(item) {
            Some(t) => out.items.push((i, t)),
            None => {
                out.any_failed = true;
                if let Some(name) =
                    item.get_ref().as_table().and_then(|t| t.iter().find(|(k, _)| k.get_ref() == "name"))
                {
                    if let Some(s) = name.1.get_ref().as_str() {
                        out.failed_names.push(s.to_string());
                    }
                }
            }
        }
    }
    out
}
