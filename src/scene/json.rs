//! A JSON walker that remembers where it is, so that every validation error names the JSON
//! path of the offending value (`images[12].mask`) as well as the file it came from.

use glam::{DMat4, DVec3};
use serde_json::Value;
use std::path::{Path, PathBuf};

/// A validation failure: the file, the JSON path inside it and what is wrong.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{}: {}: {message}", file.display(), if path.is_empty() { "(root)" } else { path.as_str() })]
pub struct SceneError {
    pub file: PathBuf,
    pub path: String,
    pub message: String,
}

/// A value in the document together with its path.
#[derive(Clone, Copy)]
pub struct Node<'a> {
    pub value: &'a Value,
    pub path: &'a str,
    pub file: &'a Path,
}

/// An owned path for nodes created while walking (field and index lookups).
pub struct At<'a> {
    pub value: &'a Value,
    pub path: String,
    pub file: &'a Path,
}

pub type Result<T> = std::result::Result<T, SceneError>;

/// The largest magnitude a number of a scene may have: its square (lengths and dot products
/// square coordinates) stays finite in f32, whose largest value is 3.4e38.
pub const MAX_MAGNITUDE: f64 = 1e18;

impl<'a> At<'a> {
    pub fn root(value: &'a Value, file: &'a Path) -> Self {
        Self { value, path: String::new(), file }
    }

    pub fn error(&self, message: impl Into<String>) -> SceneError {
        SceneError { file: self.file.to_path_buf(), path: self.path.clone(), message: message.into() }
    }

    fn child_path(&self, key: &str) -> String {
        if self.path.is_empty() {
            key.to_string()
        } else {
            format!("{}.{key}", self.path)
        }
    }

    /// A required field of an object.
    pub fn field(&self, key: &str) -> Result<At<'a>> {
        self.opt_field(key)?.ok_or_else(|| At { value: self.value, path: self.child_path(key), file: self.file }.error("missing required field"))
    }

    /// An optional field; `null` counts as absent.
    pub fn opt_field(&self, key: &str) -> Result<Option<At<'a>>> {
        let object = self.value.as_object().ok_or_else(|| self.error(format!("expected an object, found {}", describe(self.value))))?;
        Ok(object.get(key).filter(|v| !v.is_null()).map(|value| At { value, path: self.child_path(key), file: self.file }))
    }

    pub fn array(&self) -> Result<Vec<At<'a>>> {
        let items = self.value.as_array().ok_or_else(|| self.error(format!("expected an array, found {}", describe(self.value))))?;
        Ok(items.iter().enumerate().map(|(i, value)| At { value, path: format!("{}[{i}]", self.path), file: self.file }).collect())
    }

    pub fn non_empty_array(&self) -> Result<Vec<At<'a>>> {
        let items = self.array()?;
        if items.is_empty() {
            return Err(self.error("must hold at least one entry"));
        }
        Ok(items)
    }

    pub fn entries(&self) -> Result<Vec<(String, At<'a>)>> {
        let object = self.value.as_object().ok_or_else(|| self.error(format!("expected an object, found {}", describe(self.value))))?;
        Ok(object.iter().map(|(k, value)| (k.clone(), At { value, path: self.child_path(k), file: self.file })).collect())
    }

    pub fn str(&self) -> Result<&'a str> {
        self.value.as_str().ok_or_else(|| self.error(format!("expected a string, found {}", describe(self.value))))
    }

    /// A finite number whose magnitude the f32 maths of the fit can square
    /// (`MAX_MAGNITUDE`): a value finite in f64 but not in f32 (1e39) would pass here and blow
    /// up in the fit, blamed on it. serde_json already refuses NaN and Infinity literals.
    pub fn f64(&self) -> Result<f64> {
        if let Some(literal) = self.value.as_str().and_then(|s| s.strip_prefix("\u{0}non-finite:")) {
            return Err(self.error(format!("{literal} is not a finite number (JSON has no NaN or infinity)")));
        }
        let v = self.value.as_f64().ok_or_else(|| self.error(format!("expected a number, found {}", describe(self.value))))?;
        if !v.is_finite() {
            return Err(self.error("must be finite"));
        }
        if v.abs() > MAX_MAGNITUDE {
            return Err(self.error(format!("magnitude {v:e} is beyond {MAX_MAGNITUDE:e}: umbra computes in f32, where its square overflows")));
        }
        Ok(v)
    }

    pub fn positive_f64(&self) -> Result<f64> {
        let v = self.f64()?;
        if v <= 0.0 {
            return Err(self.error(format!("must be > 0, found {v}")));
        }
        Ok(v)
    }

    pub fn i64(&self) -> Result<i64> {
        if let Some(v) = self.value.as_i64() {
            return Ok(v);
        }
        match self.value.as_f64() {
            Some(v) if v.fract() == 0.0 && v.abs() < 9.0e15 => Ok(v as i64),
            _ => Err(self.error(format!("expected an integer, found {}", describe(self.value)))),
        }
    }

    /// An index into a list of `len` entries named `what`.
    pub fn index(&self, len: usize, what: &str) -> Result<usize> {
        let v = self.i64()?;
        if v < 0 || v as u64 >= len as u64 {
            return Err(self.error(format!("index {v} out of range: {what} has {len} entries")));
        }
        Ok(v as usize)
    }

    pub fn positive_usize(&self) -> Result<usize> {
        let v = self.i64()?;
        if v <= 0 || v > u32::MAX as i64 {
            return Err(self.error(format!("must be a positive integer, found {v}")));
        }
        Ok(v as usize)
    }

    pub fn vec3(&self) -> Result<DVec3> {
        let items = self.array()?;
        if items.len() != 3 {
            return Err(self.error(format!("expected 3 numbers, found {}", items.len())));
        }
        Ok(DVec3::new(items[0].f64()?, items[1].f64()?, items[2].f64()?))
    }

    /// An RGB triple with no negative channel.
    pub fn rgb(&self) -> Result<DVec3> {
        let v = self.vec3()?;
        if v.min_element() < 0.0 {
            return Err(self.error(format!("RGB values must be >= 0, found [{}, {}, {}]", v.x, v.y, v.z)));
        }
        Ok(v)
    }

    /// A row-major 4x4 matrix `[[r0],[r1],[r2],[r3]]` whose last row is `[0, 0, 0, 1]`.
    pub fn mat4(&self) -> Result<DMat4> {
        let m = self.square::<4>()?;
        if (m[3][0].abs() + m[3][1].abs() + m[3][2].abs() + (m[3][3] - 1.0).abs()) > 1e-6 {
            return Err(self.array()?[3].error(format!("the last row must be [0, 0, 0, 1], found {:?}", m[3])));
        }
        // glam is column-major: column j holds m[0..4][j].
        Ok(DMat4::from_cols_array_2d(&[
            [m[0][0], m[1][0], m[2][0], m[3][0]],
            [m[0][1], m[1][1], m[2][1], m[3][1]],
            [m[0][2], m[1][2], m[2][2], m[3][2]],
            [m[0][3], m[1][3], m[2][3], m[3][3]],
        ]))
    }

    /// A row-major N x N matrix `[[r0], ...]`, rows as written.
    fn square<const N: usize>(&self) -> Result<[[f64; N]; N]> {
        let rows = self.array()?;
        if rows.len() != N {
            return Err(self.error(format!("expected a {N}x{N} matrix ({N} rows), found {} rows", rows.len())));
        }
        let mut m = [[0.0f64; N]; N];
        for (r, row) in rows.iter().enumerate() {
            let cols = row.array()?;
            if cols.len() != N {
                return Err(row.error(format!("expected {N} numbers in a matrix row, found {}", cols.len())));
            }
            for (c, col) in cols.iter().enumerate() {
                m[r][c] = col.f64()?;
            }
        }
        Ok(m)
    }

    /// A row-major 3x3 rotation: orthonormal with determinant +1, both to 1e-3.
    pub fn rotation(&self) -> Result<glam::DMat3> {
        let m = glam::DMat3::from_cols_array_2d(&self.square::<3>()?).transpose();
        if let Err(why) = crate::skeleton::check_rigid(&DMat4::from_mat3(m), 1e-3) {
            return Err(self.error(format!("not a rotation: {why}")));
        }
        Ok(m)
    }

    /// A rigid transform: orthonormal rotation with determinant +1, both to 1e-3.
    pub fn rigid_mat4(&self) -> Result<DMat4> {
        let m = self.mat4()?;
        if let Err(why) = crate::skeleton::check_rigid(&m, 1e-3) {
            return Err(self.error(format!("not a rigid transform: {why}")));
        }
        Ok(m)
    }
}

fn describe(v: &Value) -> String {
    match v {
        Value::Null => "null".into(),
        Value::Bool(b) => format!("the boolean {b}"),
        Value::Number(n) => format!("the number {n}"),
        Value::String(s) => format!("the string {s:?}"),
        Value::Array(a) => format!("an array of {}", a.len()),
        Value::Object(_) => "an object".into(),
    }
}

/// Parses JSON text; a syntax error (truncation, a stray bracket) names line and column. A
/// bare `NaN`, `Infinity` or a number beyond f64 (`1e999`), which JSON cannot hold but
/// exporters write, is instead reported by the JSON path of the value it stands for
/// (`cameras[0].fx: NaN is not a finite number`): the text is parsed again with each such
/// literal replaced by a marker string that `At::f64` recognises.
pub fn parse(text: &str, file: &Path) -> Result<Value> {
    // A byte-order mark, as some Windows editors and exporters write before UTF-8 JSON, is no
    // part of the document.
    let text = text.strip_prefix('\u{feff}').unwrap_or(text);
    serde_json::from_str(text).or_else(|e| {
        let (marked, found) = mark_non_finite_literals(text);
        match serde_json::from_str(&marked) {
            Ok(value) if found => Ok(value),
            _ => Err(SceneError {
                file: file.to_path_buf(),
                path: String::new(),
                message: format!("invalid JSON at line {}, column {}: {e}", e.line(), e.column()),
            }),
        }
    })
}

/// The string a non-finite literal is replaced by before the second parse.
const NON_FINITE_MARK: &str = "\\u0000non-finite:";

/// `text` with every `NaN`, `Infinity`, `-Infinity` and overflowing number outside strings
/// replaced by a JSON string holding `NON_FINITE_MARK` and the literal; whether any was found.
fn mark_non_finite_literals(text: &str) -> (String, bool) {
    // Byte by byte: what is copied is copied whole, byte for byte (a string's UTF-8 included),
    // and what is inserted is ASCII, so the result is UTF-8 again.
    let bytes = text.as_bytes();
    let mut out: Vec<u8> = Vec::with_capacity(text.len());
    let (mut i, mut found, mut in_string) = (0, false, false);
    while i < bytes.len() {
        let c = bytes[i];
        if in_string {
            if c == b'\\' && i + 1 < bytes.len() {
                out.extend_from_slice(&bytes[i..i + 2]);
                i += 2;
                continue;
            }
            in_string = c != b'"';
            out.push(c);
            i += 1;
            continue;
        }
        if c == b'"' {
            in_string = true;
            out.push(b'"');
            i += 1;
            continue;
        }
        // A token of letters, digits, signs and dots (all ASCII): a literal or a number.
        let end = i + bytes[i..].iter().take_while(|b| b.is_ascii_alphanumeric() || matches!(b, b'+' | b'-' | b'.')).count();
        if end > i {
            let token = std::str::from_utf8(&bytes[i..end]).unwrap_or_default();
            let non_finite = matches!(token, "NaN" | "-NaN" | "Infinity" | "-Infinity" | "+Infinity") || token.parse::<f64>().is_ok_and(|v| !v.is_finite());
            if non_finite {
                out.extend_from_slice(format!("\"{NON_FINITE_MARK}{token}\"").as_bytes());
                found = true;
            } else {
                out.extend_from_slice(&bytes[i..end]);
            }
            i = end;
            continue;
        }
        // Everything else (punctuation, whitespace, other UTF-8) is copied as it is.
        out.push(c);
        i += 1;
    }
    (String::from_utf8(out).unwrap_or_else(|_| text.to_string()), found)
}

#[cfg(test)]
mod tests {
    use super::mark_non_finite_literals;

    #[test]
    fn non_finite_literals_are_marked_and_every_other_byte_is_kept() {
        // An escape before a two-byte character inside a string, other UTF-8 outside and inside.
        let text = "{\"\\ݣ é\": NaN, \"name\": \"héllo ݣ\", \"x\": [1e999, -Infinity, 2.5]}";
        let (marked, found) = mark_non_finite_literals(text);
        assert!(found);
        assert!(marked.contains("\"\\ݣ é\"") && marked.contains("\"héllo ݣ\"") && marked.contains("2.5"), "{marked}");
        assert_eq!(marked.matches("non-finite:").count(), 3, "{marked}");
        let (same, none) = mark_non_finite_literals("{\"ä\": [1, 2]}");
        assert!(!none && same == "{\"ä\": [1, 2]}");
    }
}
