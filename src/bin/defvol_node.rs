//! `defvol_node`: the node under the name ROS 2 users expect (`ros2 run defvol defvol_node
//! --ros-args …`); the same as `defvol node`.

fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| "info,rustdds=error,ros2_client=warn".into()),
        )
        .with_target(false)
        .init();
    let args: Vec<String> = std::env::args().skip(1).collect();
    let settings = defvol::ros::node::settings_from_args(&args)?;
    defvol::ros::node::run(settings)?;
    Ok(())
}
