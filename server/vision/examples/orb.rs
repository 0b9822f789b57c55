//! ORB extraction on one image, for profiles: `orb IMAGE [RUNS]` extracts RUNS times (1 by
//! default) on one OpenCV thread, so that `valgrind --tool=callgrind` counts the same
//! instructions on every run (wall time on a shared machine does not repeat).
use vsgraphs_vision::orb::{OrbExtractor, OrbParams};
use vsgraphs_vision::GreyImage;

fn main() {
    let mut args = std::env::args().skip(1);
    let path = args.next().expect("usage: orb IMAGE [RUNS]");
    let runs: usize = args
        .next()
        .map_or(1, |r| r.parse().expect("RUNS is a number"));
    opencv::core::set_num_threads(1).expect("OpenCV threads");
    let grey = GreyImage::read(path.as_ref()).expect("readable image");
    let mut extractor = OrbExtractor::new(OrbParams::default()).expect("extractor");
    let mut features = 0;
    for _ in 0..runs {
        features = extractor
            .extract(&grey, None)
            .expect("extraction")
            .features
            .len();
    }
    println!("{features} features");
}
