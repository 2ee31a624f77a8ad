//! `defvol_node`: the node under the name ROS 2 users expect (`ros2 run defvol defvol_node
//! --ros-args …`); the same as `defvol node`.

fn main() -> std::process::ExitCode {
    defvol::logging::init();
    let args: Vec<String> = std::env::args().skip(1).collect();
    match defvol::ros::node::run_from_args(&args) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("Error: {}", defvol::logging::error_chain(&e));
            std::process::ExitCode::FAILURE
        }
    }
}
