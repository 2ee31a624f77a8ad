//! `defvol_node`: the node under the name ROS 2 users expect (`ros2 run defvol defvol_node
//! --ros-args …`); the same as `defvol node`.

fn main() -> anyhow::Result<()> {
    defvol::logging::init();
    let args: Vec<String> = std::env::args().skip(1).collect();
    defvol::ros::node::run_from_args(&args)?;
    Ok(())
}
