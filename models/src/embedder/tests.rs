//! The embedder's tests: file format, fusion, embedding.

use super::*;
use crate::net::TestView;

fn sample(phase: f32) -> Resampled {
    let mut x = [[0.0f32; guardian_shared::trajectory::SLOTS]; STEPS];
    for (t, w) in x.iter_mut().enumerate() {
        let s = t as f32 / STEPS as f32;
        let row = [
            0.1 * (6.0 * s + phase).sin(),
            0.2 + 0.1 * (4.0 * s + phase).cos(),
            0.0,
            -2.0 + 0.1 * s,
            0.0,
            2.2,
            0.78,
        ];
        *w = guardian_shared::trajectory::waypoint(&row, if t % 40 < 30 { 1.0 } else { 0.0 });
    }
    x
}

fn assert_send_sync<T: Send + Sync>() {}

#[test]
fn round_trip_is_exact_and_versioned() {
    assert_send_sync::<Embedder>();
    let e = Embedder::random(5);
    assert_eq!(e.version().len(), 16);
    assert_eq!(Embedder::random(5).version(), e.version());
    assert_ne!(Embedder::random(6).version(), e.version());
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.safetensors");
    e.save(&path).unwrap();
    let back = Embedder::load(&path).unwrap();
    assert_eq!(back.version(), e.version());
    let xs = [sample(0.0), sample(1.0)];
    let a = e
        .embed_batch(guardian_robot::kinematics::default_panda(), &xs)
        .unwrap();
    let b = back
        .embed_batch(guardian_robot::kinematics::default_panda(), &xs)
        .unwrap();
    assert_eq!(a, b);
    assert_eq!(
        e.embed(guardian_robot::kinematics::default_panda(), &xs[1])
            .unwrap(),
        a[1]
    );
    let norm: f32 = a[0].iter().map(|v| v * v).sum();
    assert!((norm - 1.0).abs() < 1e-4);
    assert!(sq_dist(&a[0], &a[1]) > 0.0);
    assert_eq!(sq_dist(&a[0], &a[0]), 0.0);
    // No temporary file is left behind.
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
}

#[test]
fn reverse_averaging_makes_drawing_direction_irrelevant() {
    let mut e = Embedder::random(3);
    let x = sample(0.3);
    let mut rev = x;
    rev.reverse();
    let plain = e
        .embed_batch(guardian_robot::kinematics::default_panda(), &[x, rev])
        .unwrap();
    assert!(sq_dist(&plain[0], &plain[1]) > 1e-6);
    e.set_reverse_average(true);
    let version = e.version().to_string();
    let avg = e
        .embed_batch(guardian_robot::kinematics::default_panda(), &[x, rev])
        .unwrap();
    assert!(sq_dist(&avg[0], &avg[1]) < 1e-8);
    assert_eq!(e.version(), version);
    // The option survives a save/load round trip.
    let back = Embedder::from_bytes(&e.to_bytes().unwrap()).unwrap();
    assert!(back.configs()[0].reverse_average);
    assert_eq!(
        back.embed(guardian_robot::kinematics::default_panda(), &x)
            .unwrap(),
        avg[0]
    );
}

#[test]
fn test_views_average_the_plans_views_and_survive_a_round_trip() {
    let panda = guardian_robot::kinematics::default_panda();
    let mut e = Embedder::fuse(&[
        branch(FeatureKind::Pen, 21),
        branch(FeatureKind::Picture, 22),
    ])
    .unwrap();
    let xs = [sample(0.3), sample(1.1)];
    let plain = e.embed_batch(panda, &xs).unwrap();
    let (flops, version, sum) = (e.flops(), e.version().to_string(), e.checksum().to_string());
    // A view that changes nothing averages to the plan's own embedding.
    e.set_test_views(&[TestView::default()]).unwrap();
    let same = e.embed_batch(panda, &xs).unwrap();
    for (a, b) in plain.iter().zip(&same) {
        assert!(sq_dist(a, b) < 1e-10, "{}", sq_dist(a, b));
    }
    assert_eq!(e.flops(), 2 * flops);
    // Rotated and stretched views move it, and it stays a unit vector.
    let views: Vec<TestView> = ["r150", "r-150", "s100+x-80"]
        .iter()
        .map(|v| v.parse().unwrap())
        .collect();
    // Its own version (a bank enrolled without the views is not one enrolled with them);
    // the weights' checksum is unchanged.
    let identity_version = e.version().to_string();
    e.set_test_views(&views).unwrap();
    assert_ne!(e.version(), version);
    assert_ne!(e.version(), identity_version);
    assert_eq!(e.checksum(), sum);
    let mut other = e.clone();
    other.set_test_views(&views[..2]).unwrap();
    assert_ne!(other.version(), e.version());
    assert_eq!(e.flops(), 4 * flops);
    let viewed = e.embed_batch(panda, &xs).unwrap();
    for (a, b) in plain.iter().zip(&viewed) {
        assert!(sq_dist(a, b) > 1e-6);
        let norm: f32 = b.iter().map(|v| v * v).sum();
        assert!((norm - 1.0).abs() < 1e-4, "{norm}");
    }
    let back = Embedder::from_bytes(&e.to_bytes().unwrap()).unwrap();
    assert!(back.configs().iter().all(|c| c.test_views == views));
    assert_eq!(back.version(), e.version());
    assert_eq!(back.embed_batch(panda, &xs).unwrap(), viewed);
    // Without views the file's config says nothing of them (files written before them
    // read the same).
    e.set_test_views(&[]).unwrap();
    assert_eq!(e.version(), version);
    assert!(
        !e.config_json().contains("test-views"),
        "{}",
        e.config_json()
    );
    assert_eq!(e.embed_batch(panda, &xs).unwrap(), plain);
}

#[test]
fn unusable_test_views_are_refused() {
    let mut e = branch(FeatureKind::Picture, 23);
    let too_many = vec![TestView::default(); crate::net::MAX_TEST_VIEWS + 1];
    assert!(matches!(
        e.set_test_views(&too_many),
        Err(EmbedError::Config(_))
    ));
    let flat = TestView {
        stretch: 500,
        ..TestView::default()
    };
    assert!(matches!(
        e.set_test_views(&[flat]),
        Err(EmbedError::Config(_))
    ));
    let flattest = TestView {
        stretch: i16::MIN,
        ..TestView::default()
    };
    assert!(matches!(
        e.set_test_views(&[flattest]),
        Err(EmbedError::Config(_))
    ));
    assert!(e.configs()[0].test_views.is_empty());
    assert_eq!(
        "r-50+x100".parse::<TestView>().unwrap(),
        TestView {
            rotation: -50,
            shear: 0,
            stretch: 100
        }
    );
    for bad in ["q5", "r", "r99999", "r10+", "", "é5", "5"] {
        assert!(bad.parse::<TestView>().is_err(), "{bad}");
    }
}

/// A model file with one bit of its last weight flipped is refused by its checksum.
fn assert_a_flipped_bit_is_a_checksum_error(bytes: &[u8]) {
    let mut flipped = bytes.to_vec();
    let n = flipped.len();
    flipped[n - 2] ^= 0x10;
    let err = Embedder::from_bytes(&flipped).unwrap_err();
    assert!(
        matches!(err, LoadModelError::ChecksumMismatch { .. }),
        "{err}"
    );
}

/// A 64-dimensional network of `features` with random weights.
fn branch(features: FeatureKind, seed: u64) -> Embedder {
    let config = NetConfig {
        features,
        channels: vec![8, 16],
        kernel: 3,
        embed_dim: EMBED_DIM / 2,
        ..NetConfig::default()
    };
    Embedder::random_with(config, seed).unwrap()
}

#[test]
fn a_fused_model_concatenates_its_branches_and_averages_their_distances() {
    let panda = guardian_robot::kinematics::default_panda();
    let mut seq = branch(FeatureKind::Pen, 1);
    seq.set_reverse_average(true);
    let pic = branch(FeatureKind::Picture, 2);
    let xs = [sample(0.0), sample(0.7), sample(2.0)];
    let (a, b) = (
        seq.embed_batch(panda, &xs).unwrap(),
        pic.embed_batch(panda, &xs).unwrap(),
    );
    // A branch alone: its 64 values, then zeros.
    assert!(
        a.iter()
            .all(|e| e[EMBED_DIM / 2..].iter().all(|v| *v == 0.0))
    );
    let fused = Embedder::fuse(&[seq.clone(), pic.clone()]).unwrap();
    assert_eq!(fused.nets().len(), 2);
    let f = fused.embed_batch(panda, &xs).unwrap();
    let h = std::f32::consts::FRAC_1_SQRT_2;
    for ((f, a), b) in f.iter().zip(&a).zip(&b) {
        for (got, want) in f.iter().zip(a[..64].iter().chain(&b[..64])) {
            assert!((got - want * h).abs() <= 1e-6, "{got} vs {}", want * h);
        }
        let norm: f32 = f.iter().map(|v| v * v).sum();
        assert!((norm - 1.0).abs() < 1e-4, "{norm}");
    }
    // A fused distance is the mean of the branches' distances.
    for (i, j) in [(0, 1), (0, 2), (1, 2)] {
        let want = (sq_dist(&a[i], &a[j]) + sq_dist(&b[i], &b[j])) / 2.0;
        let got = sq_dist(&f[i], &f[j]);
        assert!((got - want).abs() <= 1e-5, "{got} vs {want}");
        assert!(got > 0.0);
    }
    // The pen path comes out as from a single network.
    let (e, path) = fused.embed_with_pen_path(panda, &xs[1]).unwrap();
    assert_eq!(e, f[1]);
    assert_eq!(path, guardian_robot::pen::pen_path_with(panda, &xs[1]));
    // The file round-trips with both branches, under a version of its own.
    let bytes = fused.to_bytes().unwrap();
    let back = Embedder::from_bytes(&bytes).unwrap();
    assert_eq!(back.version(), fused.version());
    assert_ne!(fused.version(), seq.version());
    assert_ne!(fused.version(), pic.version());
    assert_eq!(back.embed_batch(panda, &xs).unwrap(), f);
    assert_eq!(back.configs()[0].features, FeatureKind::Pen);
    assert!(back.configs()[0].reverse_average);
    assert_eq!(back.configs()[1].features, FeatureKind::Picture);
    // The branch order is part of the model.
    let swapped = Embedder::fuse(&[pic, seq]).unwrap();
    assert_ne!(swapped.version(), fused.version());
    // A flipped bit in a branch is a checksum error.
    assert_a_flipped_bit_is_a_checksum_error(&bytes);
}

#[test]
fn a_fused_model_that_cannot_be_served_is_refused() {
    // Two 128-dimensional networks do not fit one embedding.
    let err = Embedder::fuse(&[Embedder::random(1), Embedder::random(2)]).unwrap_err();
    assert!(
        matches!(&err, LoadModelError::BadMetadata { key: "config", got, .. } if got == "256"),
        "{err}"
    );
    // A branch without L2 normalisation would weigh its distances arbitrarily.
    let raw = Embedder::random_with(
        NetConfig {
            l2_normalize: false,
            embed_dim: 64,
            ..NetConfig::default()
        },
        3,
    )
    .unwrap();
    let err = Embedder::fuse(&[raw.clone(), branch(FeatureKind::Picture, 4)]).unwrap_err();
    assert!(err.to_string().contains("L2-normalised"), "{err}");
    // Alone, the same network is a model of its own.
    assert!(Embedder::fuse(&[raw]).is_ok());
    // A file whose config array names an unknown feature kind is refused by name.
    let fused =
        Embedder::fuse(&[branch(FeatureKind::Pen, 5), branch(FeatureKind::Picture, 6)]).unwrap();
    let bytes = fused.to_bytes().unwrap();
    let edited = edit_header(
        &bytes,
        r#"\"features\":\"picture\""#,
        r#"\"features\":\"sonar\""#,
    );
    match Embedder::from_bytes(&edited).unwrap_err() {
        LoadModelError::UnknownFeatureKind { got } => assert_eq!(got, "sonar"),
        other => panic!("expected UnknownFeatureKind, got {other}"),
    }
}

#[test]
fn corrupt_files_are_refused() {
    let e = Embedder::random(1);
    let bytes = e.to_bytes().unwrap();
    // Truncated.
    let err = Embedder::from_bytes(&bytes[..bytes.len() - 10]).unwrap_err();
    assert!(matches!(err, LoadModelError::Format(_)), "{err}");
    assert_a_flipped_bit_is_a_checksum_error(&bytes);
    // Wrong shape: a file for another architecture, relabelled with this config.
    let other = Embedder::random_with(
        NetConfig {
            channels: vec![32, 128, 128],
            ..NetConfig::default()
        },
        1,
    )
    .unwrap();
    let other_bytes = other.to_bytes().unwrap();
    let mut wrong = other_bytes.clone();
    let pat = b"[32,128,128]";
    let at = wrong
        .windows(pat.len())
        .position(|w| w == pat)
        .expect("config in header");
    wrong[at..at + pat.len()].copy_from_slice(b"[64,128,128]");
    // The header length stays the same, so it still parses; the shapes must not pass.
    let err = Embedder::from_bytes(&wrong).unwrap_err();
    assert!(matches!(err, LoadModelError::ShapeMismatch { .. }), "{err}");
    // Not a model at all.
    let err = Embedder::from_bytes(b"hello").unwrap_err();
    assert!(matches!(err, LoadModelError::Format(_)), "{err}");
    let err = Embedder::load(Path::new("/nonexistent/model.safetensors")).unwrap_err();
    assert!(matches!(err, LoadModelError::Read { .. }), "{err}");
}

/// `bytes` with the JSON header's `from` replaced by `to` (the header re-padded to 8).
fn edit_header(bytes: &[u8], from: &str, to: &str) -> Vec<u8> {
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let header = std::str::from_utf8(&bytes[8..8 + n]).unwrap();
    assert!(header.contains(from), "{header}");
    let mut header = header.trim_end().replace(from, to).into_bytes();
    header.resize(header.len().next_multiple_of(8), b' ');
    let mut out = (header.len() as u64).to_le_bytes().to_vec();
    out.extend(header);
    out.extend(&bytes[8 + n..]);
    out
}

#[test]
fn a_model_file_with_an_unknown_feature_kind_is_refused() {
    let model = Embedder::random(2);
    let bytes = model.to_bytes().unwrap();
    let kind = serde_json::to_value(model.configs()[0].features).unwrap();
    let kind = kind.as_str().unwrap().to_string();
    // The config is a JSON string inside the JSON header, so its quotes are escaped.
    let field = |k: &str| format!(r#"\"features\":\"{k}\""#);
    // The edit itself keeps a loadable file: only the feature kind decides.
    Embedder::from_bytes(&edit_header(&bytes, &field(&kind), &field(&kind)))
        .expect("an unedited config loads");
    // A kind that was removed (pen-down strokes) or never existed is refused, by name.
    for unknown in ["pen-strokes", "sonar"] {
        let edited = edit_header(&bytes, &field(&kind), &field(unknown));
        let err = Embedder::from_bytes(&edited).unwrap_err();
        match &err {
            LoadModelError::UnknownFeatureKind { got } => assert_eq!(got, unknown),
            other => panic!("expected UnknownFeatureKind, got {other}"),
        }
        assert!(err.to_string().contains(unknown), "{err}");
    }
}
