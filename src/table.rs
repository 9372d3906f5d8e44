//! CSV tables: every CSV file umbra writes goes through `to_csv`, and `read_csv` reads one back,
//! so a field holding a comma or a quote (a light's or a method's name) is quoted and the file
//! reads with any CSV reader.

/// A CSV table (`\n` line ends, fields quoted only where they need it) of `header` and `rows`.
pub fn to_csv<R, F>(header: &[&str], rows: impl IntoIterator<Item = R>) -> String
where
    R: IntoIterator<Item = F>,
    F: AsRef<str>,
{
    let mut writer = csv::WriterBuilder::new().terminator(csv::Terminator::Any(b'\n')).flexible(true).from_writer(Vec::new());
    // Writing into memory cannot fail but for a row of another width, which `flexible` allows.
    let _ = writer.write_record(header);
    for row in rows {
        let row: Vec<F> = row.into_iter().collect();
        let _ = writer.write_record(row.iter().map(|f| f.as_ref()));
    }
    let bytes = writer.into_inner().unwrap_or_default();
    String::from_utf8(bytes).unwrap_or_default()
}

/// The header and rows of a CSV table (`to_csv`'s); rows may be shorter or longer than the
/// header.
pub fn read_csv(text: &str) -> Result<(Vec<String>, Vec<Vec<String>>), String> {
    let mut reader = csv::ReaderBuilder::new().flexible(true).from_reader(text.as_bytes());
    let header = reader.headers().map_err(|e| e.to_string())?.iter().map(String::from).collect();
    let mut rows = Vec::new();
    for record in reader.records() {
        rows.push(record.map_err(|e| e.to_string())?.iter().map(String::from).collect());
    }
    Ok((header, rows))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fields_with_commas_and_quotes_read_back_as_written() {
        let rows = vec![
            vec!["closed form, 8 lanes, AVX2".to_string(), "1.5".into()],
            vec!["a \"quoted\" name".into(), String::new()],
            vec!["plain".into(), "2".into()],
        ];
        let text = to_csv(&["method", "seconds"], rows.clone());
        assert!(text.starts_with("method,seconds\n\"closed form, 8 lanes, AVX2\",1.5\n"), "{text}");
        assert!(text.ends_with("plain,2\n"), "plain fields are not quoted: {text}");
        let (header, back) = read_csv(&text).unwrap();
        assert_eq!(header, ["method", "seconds"]);
        assert_eq!(back, rows);
    }
}
