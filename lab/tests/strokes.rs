//! The stroke reader on the real shared Omniglot files and on malformed ones.

use std::path::{Path, PathBuf};

use guardian_omniglot::strokes::{ReadStrokesError, parse_strokes, read_strokes, scan};

/// `<workspace root>/../shared/omniglot/strokes`.
fn shared_strokes() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/omniglot/strokes")
}

#[test]
fn scans_the_shared_set_in_class_order() {
    let files = scan(&[shared_strokes()]).expect("shared strokes");
    assert_eq!(files.len(), 3660);
    let mut classes: Vec<String> = files.iter().map(|f| f.class_name()).collect();
    classes.dedup();
    assert_eq!(classes.len(), 183);
    let mut sorted = classes.clone();
    sorted.sort();
    assert_eq!(classes, sorted, "files come sorted by alphabet, character");
    let mut alphabets: Vec<&str> = files.iter().map(|f| f.alphabet.as_str()).collect();
    alphabets.dedup();
    assert_eq!(alphabets.len(), 6);
    for class in files.chunk_by(|a, b| a.class_name() == b.class_name()) {
        let drawers: Vec<u32> = class.iter().map(|f| f.drawer).collect();
        assert_eq!(
            drawers,
            (1..=20).collect::<Vec<_>>(),
            "{}",
            class[0].class_name()
        );
    }
    let latin = files
        .iter()
        .find(|f| f.class_name() == "Latin/character01" && f.drawer == 1)
        .expect("Latin/character01 drawer 1");
    assert_eq!(latin.character_id, 683);
}

#[test]
fn reads_every_shared_file_and_a_known_one_exactly() {
    let files = scan(&[shared_strokes()]).expect("shared strokes");
    let mut dots = 0;
    for f in &files {
        let strokes = read_strokes(&f.path).unwrap_or_else(|e| panic!("{e}"));
        assert!(!strokes.is_empty());
        dots += strokes.iter().filter(|s| s.len() == 1).count();
    }
    assert!(dots > 0, "the shared set has one-point strokes (dots)");
    let s = read_strokes(&shared_strokes().join("Latin/character01/0683_01.txt")).expect("read");
    assert_eq!(s[0][0].x, 68.75);
    assert_eq!(s[0][0].y, -25.859438);
    assert_eq!(s[0][0].t, 0.0);
    assert_eq!(s[0].len(), 14);
    assert_eq!(s[0][13].y, -69.859438);
}

#[test]
fn the_official_release_layout_is_read_unchanged() {
    let dir = tempfile::tempdir().expect("tempdir");
    let root = dir.path().join("strokes_background");
    let char_dir = root.join("Latin/character01");
    std::fs::create_dir_all(&char_dir).expect("mkdir");
    for d in ["01", "02"] {
        let name = format!("0683_{d}.txt");
        std::fs::copy(
            shared_strokes().join("Latin/character01").join(&name),
            char_dir.join(&name),
        )
        .expect("copy");
    }
    std::fs::write(root.join("Latin/.DS_Store"), b"junk").expect("write");
    let files = scan(&[root]).expect("scan");
    assert_eq!(files.len(), 2);
    assert_eq!(files[1].class_name(), "Latin/character01");
    assert_eq!(files[1].drawer, 2);
}

fn write(dir: &Path, name: &str, text: &[u8]) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, text).expect("write");
    p
}

#[test]
fn malformed_files_are_typed_errors_naming_file_and_line() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();

    let p = write(d, "bad_number.txt", b"START\n1,-2,0\n3,-4x,10\nBREAK\n");
    match read_strokes(&p) {
        Err(e @ ReadStrokesError::BadNumber { line: 3, .. }) => {
            let msg = e.to_string();
            assert!(msg.contains("bad_number.txt:3"), "{msg}");
            assert!(msg.contains("-4x"), "{msg}");
        }
        other => panic!("expected BadNumber at line 3, got {other:?}"),
    }

    let p = write(d, "nan.txt", b"START\nNaN,-2,0\nBREAK\n");
    assert!(matches!(
        read_strokes(&p),
        Err(ReadStrokesError::BadNumber { line: 2, .. })
    ));

    let p = write(d, "no_start.txt", b"1,-2,0\n3,-4,10\nBREAK\n");
    match read_strokes(&p) {
        Err(e @ ReadStrokesError::MissingStart { line: 1, .. }) => {
            assert!(e.to_string().contains("no_start.txt:1"), "{e}");
        }
        other => panic!("expected MissingStart, got {other:?}"),
    }

    let p = write(d, "empty.txt", b"START\nBREAK\n");
    match read_strokes(&p) {
        Err(e @ ReadStrokesError::Empty { .. }) => assert!(e.to_string().contains("empty.txt")),
        other => panic!("expected Empty, got {other:?}"),
    }
    let p = write(d, "zero.txt", b"");
    assert!(matches!(
        read_strokes(&p),
        Err(ReadStrokesError::Empty { .. })
    ));

    let p = write(d, "two_fields.txt", b"START\n1,-2\nBREAK\n");
    assert!(matches!(
        read_strokes(&p),
        Err(ReadStrokesError::BadLine { line: 2, .. })
    ));

    // Not UTF-8: unreadable as text.
    let p = write(d, "binary.txt", &[0xff, 0xfe, 0x00, 0x41]);
    match read_strokes(&p) {
        Err(e @ ReadStrokesError::Io { .. }) => assert!(e.to_string().contains("binary.txt")),
        other => panic!("expected Io, got {other:?}"),
    }
    let missing = d.join("missing.txt");
    assert!(matches!(
        read_strokes(&missing),
        Err(ReadStrokesError::Io { .. })
    ));

    // Parsing text directly reports the given path.
    let e = parse_strokes("START\n1,2,three\n", Path::new("A/character01/0001_01.txt"))
        .expect_err("bad number");
    assert!(e.to_string().contains("A/character01/0001_01.txt:2"), "{e}");
}

#[test]
fn bad_layouts_are_typed_errors() {
    let dir = tempfile::tempdir().expect("tempdir");
    let root = dir.path().join("strokes");
    let c = root.join("Latin/character01");
    std::fs::create_dir_all(&c).expect("mkdir");
    write(&c, "683-1.txt", b"START\n1,-2,0\nBREAK\n");
    assert!(matches!(
        scan(std::slice::from_ref(&root)),
        Err(ReadStrokesError::FileName { .. })
    ));

    let empty = dir.path().join("empty_root");
    std::fs::create_dir_all(&empty).expect("mkdir");
    assert!(matches!(
        scan(&[empty]),
        Err(ReadStrokesError::NoFiles { .. })
    ));
    assert!(matches!(
        scan(&[dir.path().join("nowhere")]),
        Err(ReadStrokesError::Io { .. })
    ));
    // The same alphabet under two roots is refused.
    std::fs::remove_file(c.join("683-1.txt")).expect("rm");
    write(&c, "0683_01.txt", b"START\n1,-2,0\nBREAK\n");
    assert!(matches!(
        scan(&[root.clone(), root]),
        Err(ReadStrokesError::DuplicateAlphabet { .. })
    ));
}
