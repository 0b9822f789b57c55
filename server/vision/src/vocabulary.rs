//! Visual words for place recognition: a tree of binary descriptors, each node the bitwise
//! majority of the descriptors under it (hierarchical k-medians, as bags of binary words
//! build it), so that a descriptor finds its word in `branching × depth` Hamming distances.
//! An image becomes a bag of words: each word weighted by how rare it was in the training
//! images (inverse document frequency) and by how often the image holds it, scaled to sum 1,
//! so two bags compare by the weight they share ([`score`]).
//!
//! Written here rather than taken from a crate: the Rust ones found (`abow`) are unmaintained,
//! have no grouping of features by node (which verification needs to match only descriptors
//! of one node) and use their own file format; the tree is a few hundred lines.
//! `vsgraphs-eval vocabulary` trains the one the server ships (BENCHMARKS.md says how).

use crate::brief::{hamming, Descriptor};
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

/// Index of a word (a leaf of the tree), dense from 0.
pub type WordId = u32;
/// Index of a node of the tree, breadth-first from the root (0).
pub type NodeId = u32;

/// A file could not be read as a vocabulary, or training had nothing to learn from.
#[derive(Debug, thiserror::Error)]
pub enum VocabularyError {
    #[error("reading {path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("not a vocabulary: {0}")]
    Format(String),
    #[error("cannot train a vocabulary: {0}")]
    Training(String),
}

/// The tree and its words' weights.
#[derive(Clone, Debug, PartialEq)]
pub struct Vocabulary {
    branching: usize,
    depth: usize,
    /// Breadth-first; node 0 is the root, whose descriptor is unused. A node's children are
    /// contiguous.
    nodes: Vec<Node>,
    /// Inverse document frequency of each word, by word id.
    weights: Vec<f32>,
}

#[derive(Clone, Debug, PartialEq)]
struct Node {
    descriptor: Descriptor,
    first_child: u32,
    children: u16,
    /// The root is level 0.
    level: u8,
    /// The word of a leaf; `NO_WORD` for inner nodes.
    word: WordId,
}

const NO_WORD: WordId = WordId::MAX;
const MAGIC: &[u8; 8] = b"VSGVOCAB";
const VERSION: u32 = 1;

/// An image as words: which words it holds with what weight, and which of its features fall
/// under each node of one level (to match descriptors node by node).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct BagOfWords {
    /// Sorted by word; weights sum to 1 (none when the image had no features).
    pub words: Vec<(WordId, f32)>,
    /// Sorted by node; feature indices ascending within each.
    pub features_by_node: Vec<(NodeId, Vec<u32>)>,
}

/// Similarity of two bags in [0, 1]: the weight they share, `Σ min(a_w, b_w)` (the L1 score
/// of bags of words, `1 − ½‖a − b‖₁`, for bags that each sum to 1).
pub fn score(a: &BagOfWords, b: &BagOfWords) -> f32 {
    let (mut i, mut j, mut shared) = (0, 0, 0.0);
    while i < a.words.len() && j < b.words.len() {
        let (wa, va) = a.words[i];
        let (wb, vb) = b.words[j];
        match wa.cmp(&wb) {
            std::cmp::Ordering::Less => i += 1,
            std::cmp::Ordering::Greater => j += 1,
            std::cmp::Ordering::Equal => {
                shared += va.min(vb);
                i += 1;
                j += 1;
            }
        }
    }
    shared
}

/// How a vocabulary is trained.
#[derive(Clone, Debug, PartialEq)]
pub struct Training {
    /// Children per node.
    pub branching: usize,
    /// Levels below the root; at most `branching ^ depth` words.
    pub depth: usize,
    /// k-medians rounds per node at most (it stops earlier when no descriptor changes cluster).
    pub iterations: usize,
    /// Seeds the choice of first centres; the same seed and input give the same tree.
    pub seed: u64,
}

impl Default for Training {
    fn default() -> Self {
        Self {
            branching: 10,
            depth: 4,
            iterations: 10,
            seed: 1,
        }
    }
}

impl Vocabulary {
    /// The vocabulary the server ships, trained on simulated frames (BENCHMARKS.md).
    pub fn builtin() -> &'static Vocabulary {
        static BUILTIN: OnceLock<Vocabulary> = OnceLock::new();
        BUILTIN.get_or_init(|| {
            Vocabulary::from_bytes(include_bytes!("../vocabulary/orb-k10-l4.voc"))
                .expect("the shipped vocabulary is valid (a test reads it)")
        })
    }

    /// Trains a tree on the descriptors of `images` (one list per image) and weighs its words
    /// by the images they occur in.
    pub fn train(images: &[Vec<Descriptor>], training: &Training) -> Result<Self, VocabularyError> {
        if !(2..=u16::MAX as usize).contains(&training.branching) {
            return Err(VocabularyError::Training(format!(
                "branching {} is not in 2..=65535",
                training.branching
            )));
        }
        if !(1..=16).contains(&training.depth) {
            return Err(VocabularyError::Training(format!(
                "depth {} is not in 1..=16",
                training.depth
            )));
        }
        let all: Vec<Descriptor> = images.iter().flatten().copied().collect();
        if all.is_empty() {
            return Err(VocabularyError::Training("no descriptors".into()));
        }
        let mut random = SplitMix(training.seed);
        let mut nodes = vec![Node {
            descriptor: [0; 32],
            first_child: 0,
            children: 0,
            level: 0,
            word: NO_WORD,
        }];
        // Breadth-first, so each node's children are appended together.
        let mut queue = std::collections::VecDeque::from([(0usize, (0..all.len()).collect())]);
        while let Some((parent, members)) = queue.pop_front() {
            let members: Vec<usize> = members;
            let level = nodes[parent].level;
            if usize::from(level) == training.depth || members.len() <= 1 {
                continue;
            }
            let clusters = if members.len() <= training.branching {
                members.iter().map(|&m| (all[m], vec![m])).collect()
            } else {
                k_medians(&all, &members, training, &mut random)
            };
            nodes[parent].first_child = nodes.len() as u32;
            nodes[parent].children = clusters.len() as u16;
            for (centre, cluster) in clusters {
                queue.push_back((nodes.len(), cluster));
                nodes.push(Node {
                    descriptor: centre,
                    first_child: 0,
                    children: 0,
                    level: level + 1,
                    word: NO_WORD,
                });
            }
        }
        let mut vocabulary = Self::from_tree(training.branching, training.depth, nodes, Vec::new());
        // A word's weight: ln(images / images holding it).
        let mut holding = vec![0u32; vocabulary.words()];
        for image in images {
            let mut words: Vec<WordId> = image.iter().map(|d| vocabulary.descend(d, 0).0).collect();
            words.sort_unstable();
            words.dedup();
            for w in words {
                holding[w as usize] += 1;
            }
        }
        let n = images.len() as f64;
        vocabulary.weights = holding
            .iter()
            .map(|&h| (n / f64::from(h.max(1))).ln() as f32)
            .collect();
        Ok(vocabulary)
    }

    /// Numbers the leaves as words, breadth-first.
    fn from_tree(branching: usize, depth: usize, mut nodes: Vec<Node>, weights: Vec<f32>) -> Self {
        let mut words = 0;
        for node in nodes.iter_mut().skip(1) {
            if node.children == 0 {
                node.word = words;
                words += 1;
            }
        }
        Self {
            branching,
            depth,
            nodes,
            weights,
        }
    }

    pub fn words(&self) -> usize {
        self.nodes
            .iter()
            .skip(1)
            .filter(|n| n.children == 0)
            .count()
    }

    pub fn branching(&self) -> usize {
        self.branching
    }

    pub fn depth(&self) -> usize {
        self.depth
    }

    /// A word's weight (inverse document frequency).
    pub fn weight(&self, word: WordId) -> f32 {
        self.weights[word as usize]
    }

    /// The word of a descriptor, and the node on its way down at `level` (the word's own
    /// node where the tree ends above it).
    fn descend(&self, descriptor: &Descriptor, level: usize) -> (WordId, NodeId) {
        let mut at = 0usize;
        let mut at_level = 0;
        loop {
            let node = &self.nodes[at];
            if node.children == 0 {
                return (node.word, at_level as NodeId);
            }
            let first = node.first_child as usize;
            let children = first..first + usize::from(node.children);
            at = children
                .min_by_key(|&c| hamming(descriptor, &self.nodes[c].descriptor))
                .expect("an inner node has children");
            if usize::from(self.nodes[at].level) <= level {
                at_level = at;
            }
        }
    }

    /// The word a descriptor falls into.
    pub fn word(&self, descriptor: &Descriptor) -> (WordId, f32) {
        let (word, _) = self.descend(descriptor, 0);
        (word, self.weights[word as usize])
    }

    /// An image's bag of words, its features grouped by their node at `level` of the tree
    /// (1: the root's children).
    pub fn transform(&self, descriptors: &[Descriptor], level: usize) -> BagOfWords {
        let mut words: Vec<(WordId, f32)> = Vec::with_capacity(descriptors.len());
        let mut by_node: Vec<(NodeId, u32)> = Vec::with_capacity(descriptors.len());
        for (i, d) in descriptors.iter().enumerate() {
            let (word, node) = self.descend(d, level);
            let weight = self.weights[word as usize];
            if weight > 0.0 {
                words.push((word, weight));
            }
            by_node.push((node, i as u32));
        }
        words.sort_unstable_by_key(|&(w, _)| w);
        let mut merged: Vec<(WordId, f32)> = Vec::with_capacity(words.len());
        for (w, v) in words {
            match merged.last_mut() {
                Some((last, sum)) if *last == w => *sum += v,
                _ => merged.push((w, v)),
            }
        }
        let total: f32 = merged.iter().map(|(_, v)| v).sum();
        if total > 0.0 {
            for (_, v) in &mut merged {
                *v /= total;
            }
        }
        by_node.sort_unstable();
        let mut features_by_node: Vec<(NodeId, Vec<u32>)> = Vec::new();
        for (node, i) in by_node {
            match features_by_node.last_mut() {
                Some((last, list)) if *last == node => list.push(i),
                _ => features_by_node.push((node, vec![i])),
            }
        }
        BagOfWords {
            words: merged,
            features_by_node,
        }
    }

    /// The file form: magic, version, sizes, each node's child count and descriptor
    /// breadth-first, each word's weight, and a checksum of all before it (little-endian).
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(24 + self.nodes.len() * 34 + self.weights.len() * 4 + 8);
        out.extend_from_slice(MAGIC);
        out.extend_from_slice(&VERSION.to_le_bytes());
        out.extend_from_slice(&(self.branching as u16).to_le_bytes());
        out.extend_from_slice(&(self.depth as u16).to_le_bytes());
        out.extend_from_slice(&(self.nodes.len() as u32).to_le_bytes());
        out.extend_from_slice(&(self.weights.len() as u32).to_le_bytes());
        for node in &self.nodes {
            out.extend_from_slice(&node.children.to_le_bytes());
            out.extend_from_slice(&node.descriptor);
        }
        for w in &self.weights {
            out.extend_from_slice(&w.to_le_bytes());
        }
        let sum = fnv1a(&out);
        out.extend_from_slice(&sum.to_le_bytes());
        out
    }

    /// Reads the file form, checking every size, the tree's shape and the checksum.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, VocabularyError> {
        let bad = |what: String| VocabularyError::Format(what);
        if bytes.len() < 32 || &bytes[..8] != MAGIC {
            return Err(bad("it does not start with the vocabulary magic".into()));
        }
        let (body, sum) = bytes.split_at(bytes.len() - 8);
        let sum = u64::from_le_bytes(sum.try_into().expect("8 bytes"));
        let u16_at = |at: usize| u16::from_le_bytes([body[at], body[at + 1]]);
        let u32_at = |at: usize| u32::from_le_bytes(body[at..at + 4].try_into().expect("4 bytes"));
        let version = u32_at(8);
        if version != VERSION {
            return Err(bad(format!(
                "format version {version}; this build reads {VERSION}"
            )));
        }
        let branching = usize::from(u16_at(12));
        let depth = usize::from(u16_at(14));
        let node_count = u32_at(16) as usize;
        let word_count = u32_at(20) as usize;
        let expected = 24 + node_count * 34 + word_count * 4;
        if body.len() != expected {
            return Err(bad(format!(
                "{} bytes where {node_count} nodes and {word_count} words take {expected}",
                body.len()
            )));
        }
        if fnv1a(body) != sum {
            return Err(bad(
                "its checksum does not match (corrupt or truncated)".into()
            ));
        }
        if branching < 2 || !(1..=16).contains(&depth) || node_count == 0 {
            return Err(bad(format!(
                "branching {branching}, depth {depth}, {node_count} nodes"
            )));
        }
        let mut nodes = Vec::with_capacity(node_count);
        for i in 0..node_count {
            let at = 24 + i * 34;
            nodes.push(Node {
                descriptor: body[at + 2..at + 34].try_into().expect("32 bytes"),
                first_child: 0,
                children: u16_at(at),
                level: 0,
                word: NO_WORD,
            });
        }
        // Children are contiguous and breadth-first: node i's come after those of all
        // nodes before it.
        let mut next = 1usize;
        for i in 0..node_count {
            let children = usize::from(nodes[i].children);
            if children > branching || next + children > node_count {
                return Err(bad(format!("node {i} has children beyond the tree")));
            }
            if children > 0 {
                nodes[i].first_child = next as u32;
            }
            let level = nodes[i].level + 1;
            if children > 0 && usize::from(level) > depth {
                return Err(bad(format!("node {i} has children below depth {depth}")));
            }
            for child in &mut nodes[next..next + children] {
                child.level = level;
            }
            next += children;
        }
        if next != node_count {
            return Err(bad(format!(
                "{} of {node_count} nodes are in no parent",
                node_count - next
            )));
        }
        let weights: Vec<f32> = (0..word_count)
            .map(|w| {
                let at = 24 + node_count * 34 + w * 4;
                f32::from_le_bytes(body[at..at + 4].try_into().expect("4 bytes"))
            })
            .collect();
        if let Some(w) = weights.iter().position(|w| !w.is_finite() || *w < 0.0) {
            return Err(bad(format!("word {w} has weight {}", weights[w])));
        }
        let vocabulary = Self::from_tree(branching, depth, nodes, weights);
        if vocabulary.words() != word_count {
            return Err(bad(format!(
                "{} leaves but {word_count} word weights",
                vocabulary.words()
            )));
        }
        Ok(vocabulary)
    }

    pub fn read(path: &Path) -> Result<Self, VocabularyError> {
        let bytes = std::fs::read(path).map_err(|source| VocabularyError::Io {
            path: path.to_owned(),
            source,
        })?;
        Self::from_bytes(&bytes)
    }
}

/// One node's descriptors split into at most `branching` clusters: k-means++ seeding by
/// squared Hamming distance, then rounds of assignment and bitwise majority.
fn k_medians(
    all: &[Descriptor],
    members: &[usize],
    training: &Training,
    random: &mut SplitMix,
) -> Vec<(Descriptor, Vec<usize>)> {
    let k = training.branching;
    let mut centres: Vec<Descriptor> = vec![all[members[random.below(members.len())]]];
    let mut nearest: Vec<u32> = members
        .iter()
        .map(|&m| hamming(&all[m], &centres[0]))
        .collect();
    while centres.len() < k {
        let total: f64 = nearest.iter().map(|&d| f64::from(d * d)).sum();
        if total == 0.0 {
            break; // every member equals a centre
        }
        let mut target = random.uniform() * total;
        let mut chosen = members.len() - 1;
        for (i, &d) in nearest.iter().enumerate() {
            target -= f64::from(d * d);
            if target < 0.0 {
                chosen = i;
                break;
            }
        }
        let centre = all[members[chosen]];
        for (i, &m) in members.iter().enumerate() {
            nearest[i] = nearest[i].min(hamming(&all[m], &centre));
        }
        centres.push(centre);
    }
    let mut assignment = vec![usize::MAX; members.len()];
    for _ in 0..training.iterations.max(1) {
        let mut changed = false;
        for (i, &m) in members.iter().enumerate() {
            let best = (0..centres.len())
                .min_by_key(|&c| hamming(&all[m], &centres[c]))
                .expect("at least one centre");
            changed |= assignment[i] != best;
            assignment[i] = best;
        }
        if !changed {
            break;
        }
        let mut ones = vec![[0u32; 256]; centres.len()];
        let mut sizes = vec![0u32; centres.len()];
        for (i, &m) in members.iter().enumerate() {
            let c = assignment[i];
            sizes[c] += 1;
            for (bit, count) in ones[c].iter_mut().enumerate() {
                *count += u32::from(all[m][bit / 8] >> (bit % 8) & 1);
            }
        }
        for (c, centre) in centres.iter_mut().enumerate() {
            if sizes[c] == 0 {
                continue; // keeps its place; dropped below if still empty
            }
            *centre = [0; 32];
            for (bit, &count) in ones[c].iter().enumerate() {
                if 2 * count > sizes[c] {
                    centre[bit / 8] |= 1 << (bit % 8);
                }
            }
        }
    }
    let mut clusters: Vec<(Descriptor, Vec<usize>)> =
        centres.iter().map(|&c| (c, Vec::new())).collect();
    for (i, &m) in members.iter().enumerate() {
        clusters[assignment[i]].1.push(m);
    }
    clusters.retain(|(_, list)| !list.is_empty());
    clusters
}

/// SplitMix64, enough for choosing centres reproducibly.
struct SplitMix(u64);

impl SplitMix {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    fn uniform(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64
    }

    fn below(&mut self, n: usize) -> usize {
        ((self.uniform() * n as f64) as usize).min(n - 1)
    }
}

/// FNV-1a, 64 bits: catches a flipped or lost byte.
fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, &b| {
        (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `count` random descriptors.
    fn prototypes(count: usize, random: &mut SplitMix) -> Vec<Descriptor> {
        (0..count)
            .map(|_| {
                let mut d = [0u8; 32];
                for chunk in d.chunks_mut(8) {
                    chunk.copy_from_slice(&random.next().to_le_bytes());
                }
                d
            })
            .collect()
    }

    /// A copy of `d` with `flips` random bits flipped (perhaps the same bit twice).
    fn noisy(d: &Descriptor, flips: usize, random: &mut SplitMix) -> Descriptor {
        let mut d = *d;
        for _ in 0..flips {
            let bit = random.below(256);
            d[bit / 8] ^= 1 << (bit % 8);
        }
        d
    }

    /// An image holding noisy copies of the given prototypes, `copies` of each.
    fn image(of: &[Descriptor], copies: usize, random: &mut SplitMix) -> Vec<Descriptor> {
        of.iter()
            .flat_map(|p| (0..copies).map(|_| noisy(p, 8, random)).collect::<Vec<_>>())
            .collect()
    }

    fn trained() -> (Vocabulary, Vec<Descriptor>) {
        let mut random = SplitMix(7);
        let protos = prototypes(40, &mut random);
        // Each image shows 10 of the 40 prototypes, a different window each time.
        let images: Vec<Vec<Descriptor>> = (0..40)
            .map(|i| {
                let shown: Vec<Descriptor> = (0..10).map(|k| protos[(i + k) % 40]).collect();
                image(&shown, 5, &mut random)
            })
            .collect();
        let training = Training {
            branching: 4,
            depth: 3,
            ..Training::default()
        };
        (Vocabulary::train(&images, &training).unwrap(), protos)
    }

    #[test]
    fn noisy_copies_of_one_descriptor_share_its_word_and_others_do_not() {
        let (vocabulary, protos) = trained();
        assert!(vocabulary.words() <= 64);
        let mut random = SplitMix(99);
        let mut same = 0;
        for p in &protos {
            let (word, _) = vocabulary.word(p);
            same += (0..20)
                .filter(|_| vocabulary.word(&noisy(p, 8, &mut random)).0 == word)
                .count();
        }
        assert!(
            same >= 40 * 20 * 95 / 100,
            "{same} of 800 copies in their word"
        );
        let mut words: Vec<WordId> = protos.iter().map(|p| vocabulary.word(p).0).collect();
        words.sort_unstable();
        words.dedup();
        assert!(words.len() >= 36, "40 prototypes in {} words", words.len());
    }

    #[test]
    fn bags_of_the_same_things_score_high_and_of_different_things_low() {
        let (vocabulary, protos) = trained();
        let mut random = SplitMix(5);
        let a = vocabulary.transform(&image(&protos[..10], 3, &mut random), 1);
        let again = vocabulary.transform(&image(&protos[..10], 3, &mut random), 1);
        let other = vocabulary.transform(&image(&protos[20..30], 3, &mut random), 1);
        let total: f32 = a.words.iter().map(|w| w.1).sum();
        assert!((total - 1.0).abs() < 1e-5);
        assert!(a.words.windows(2).all(|w| w[0].0 < w[1].0));
        assert!((score(&a, &a) - 1.0).abs() < 1e-5);
        assert!(score(&a, &again) > 0.8, "{}", score(&a, &again));
        assert!(score(&a, &other) < 0.15, "{}", score(&a, &other));
        // Every feature is grouped once, under a node of level 1.
        let mut grouped: Vec<u32> = a
            .features_by_node
            .iter()
            .flat_map(|n| n.1.clone())
            .collect();
        grouped.sort_unstable();
        assert_eq!(grouped, (0..30).collect::<Vec<u32>>());
        assert!(a.features_by_node.len() <= 4);
    }

    #[test]
    fn the_file_form_reads_back_and_refuses_damage() {
        let (vocabulary, _) = trained();
        let bytes = vocabulary.to_bytes();
        assert_eq!(Vocabulary::from_bytes(&bytes).unwrap(), vocabulary);
        let mut flipped = bytes.clone();
        flipped[100] ^= 1;
        let refused = |b: &[u8]| Vocabulary::from_bytes(b).unwrap_err().to_string();
        assert!(refused(&flipped).contains("checksum"));
        assert!(refused(&bytes[..bytes.len() - 9]).contains("bytes where"));
        assert!(refused(b"not a vocabulary at all, really.").contains("magic"));
        let mut newer = bytes.clone();
        newer[8] = 2;
        assert!(refused(&newer).contains("version 2"));
    }

    #[test]
    fn the_shipped_vocabulary_is_read_whole() {
        let builtin = Vocabulary::builtin();
        assert_eq!((builtin.branching(), builtin.depth()), (10, 4));
        assert!(builtin.words() > 5_000, "{} words", builtin.words());
        let file = include_bytes!("../vocabulary/orb-k10-l4.voc");
        assert_eq!(builtin.to_bytes(), file.to_vec());
    }

    #[test]
    fn training_without_descriptors_says_so() {
        let error = Vocabulary::train(&[vec![]], &Training::default()).unwrap_err();
        assert!(error.to_string().contains("no descriptors"));
    }
}
