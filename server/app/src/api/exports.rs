//! A map in the files other tools open: its points as PLY (CloudCompare, MeshLab, Open3D,
//! PCL) and its Situational Graph as GraphML (Gephi, yEd, NetworkX). The JSON forms are the
//! API's own (`/graph`, `/model`); trajectories are TUM files (`/trajectory?format=tum`).

use quick_xml::escape::escape;
use std::fmt::Write as _;
use vsgraphs_proto::api::{GraphLayer, SceneGraph};

/// The media type of GraphML.
pub const GRAPHML_TYPE: &str = "application/graphml+xml";

/// Points as a binary little-endian PLY of `x y z` floats, metres in the map's frame (the
/// compact form every PLY reader takes; a map holds up to a few hundred thousand points).
pub fn ply(points: &[[f32; 3]], comment: &str) -> Vec<u8> {
    let comment: String = comment.chars().filter(|c| !c.is_control()).collect();
    let header = format!(
        "ply\nformat binary_little_endian 1.0\ncomment {comment}\nelement vertex {}\n\
         property float x\nproperty float y\nproperty float z\nend_header\n",
        points.len()
    );
    let mut bytes = Vec::with_capacity(header.len() + points.len() * 12);
    bytes.extend_from_slice(header.as_bytes());
    for p in points {
        for c in p {
            bytes.extend_from_slice(&c.to_le_bytes());
        }
    }
    bytes
}

/// The graph as GraphML: every node with its layer, kind, name (when it has one) and position,
/// every edge from the lower layer's node to the upper's.
pub fn graphml(graph: &SceneGraph) -> String {
    let mut xml = String::from(
        "<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n\
         <graphml xmlns=\"http://graphml.graphdrawing.org/xmlns\">\n",
    );
    for (key, kind) in [
        ("layer", "string"),
        ("kind", "string"),
        ("name", "string"),
        ("x", "double"),
        ("y", "double"),
        ("z", "double"),
    ] {
        let _ = writeln!(
            xml,
            "  <key id=\"{key}\" for=\"node\" attr.name=\"{key}\" attr.type=\"{kind}\"/>"
        );
    }
    let _ = writeln!(
        xml,
        "  <graph id=\"map-{}\" edgedefault=\"directed\">",
        graph.map_id
    );
    for node in &graph.nodes {
        let layer = match node.layer {
            GraphLayer::Keyframes => "keyframes",
            GraphLayer::Structure => "structure",
            GraphLayer::Spaces => "spaces",
        };
        let _ = write!(
            xml,
            "    <node id=\"{}\"><data key=\"layer\">{layer}</data><data key=\"kind\">{}</data>",
            escape(&node.id),
            escape(&node.kind)
        );
        if let Some(name) = &node.name {
            let _ = write!(xml, "<data key=\"name\">{}</data>", escape(name));
        }
        let [x, y, z] = node.position;
        let _ = writeln!(
            xml,
            "<data key=\"x\">{x}</data><data key=\"y\">{y}</data><data key=\"z\">{z}</data></node>"
        );
    }
    for edge in &graph.edges {
        let _ = writeln!(
            xml,
            "    <edge source=\"{}\" target=\"{}\"/>",
            escape(&edge.from),
            escape(&edge.to)
        );
    }
    xml.push_str("  </graph>\n</graphml>\n");
    xml
}

#[cfg(test)]
mod tests {
    use super::*;
    use quick_xml::events::Event;
    use vsgraphs_proto::api::{GraphEdge, GraphNode};

    #[test]
    fn a_name_with_markup_stays_text_in_the_graphml() {
        let name = r#"Tom's <img src=x> "room" & co"#;
        let graph = SceneGraph {
            map_id: 3,
            nodes: vec![GraphNode {
                id: "room/0".into(),
                layer: GraphLayer::Spaces,
                kind: "room".into(),
                name: Some(name.into()),
                position: [1.5, -2.0, 0.0],
            }],
            edges: vec![GraphEdge {
                from: "wall/1".into(),
                to: "room/0".into(),
            }],
        };
        let xml = graphml(&graph);
        let mut reader = quick_xml::Reader::from_str(&xml);
        let v1 = quick_xml::XmlVersion::Implicit1_0;
        let (mut text, mut elements) = (String::new(), Vec::new());
        loop {
            match reader.read_event().expect("well-formed XML") {
                Event::Start(e) | Event::Empty(e) => elements.push(e.name().as_ref().to_owned()),
                Event::Text(t) => text.push_str(&t.xml_content(v1)),
                Event::GeneralRef(r) => text.push_str(
                    quick_xml::escape::resolve_predefined_entity(&r.xml_content(v1)).unwrap(),
                ),
                Event::Eof => break,
                _ => {}
            }
        }
        assert!(text.contains(name), "{text}");
        assert!(!elements.iter().any(|e| e == "img"), "{elements:?}");
        assert_eq!(elements.iter().filter(|e| *e == "edge").count(), 1);
    }

    #[test]
    fn a_ply_holds_its_points_after_its_header() {
        let bytes = ply(&[[1.0, 2.0, 3.0], [-0.5, 0.25, 8.0]], "map\n0");
        let header = "ply\nformat binary_little_endian 1.0\ncomment map0\nelement vertex 2\n\
                      property float x\nproperty float y\nproperty float z\nend_header\n";
        assert_eq!(&bytes[..header.len()], header.as_bytes());
        let floats: Vec<f32> = bytes[header.len()..]
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
            .collect();
        assert_eq!(floats, [1.0, 2.0, 3.0, -0.5, 0.25, 8.0]);
    }
}
