//! The live server's `parameters` capability against the robot's own parameter service: the
//! control core (`firmware::Controller`) answers each request at its next step, as on a bus.
//! A client that speaks the protocol reads every parameter, sets one (answered with the value
//! in force, and in force in the core), and has a refused value answered with the old one and
//! a `status` error naming the parameter, the value and the rule.

use std::collections::VecDeque;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use firmware::protocol::canopen::NodeId;
use firmware::{CanFrame, Config, Controller, Instant, params};
use futures_util::SinkExt as _;
use live::{LiveOptions, LiveServer};
use mecanum_linux::{FramePort, SdoClient};
use serde_json::{Value, json};
use tokio_tungstenite::tungstenite::Message;

mod common;

use common::{Ws, connect, next_json};

/// The robot: a control core stepped once per frame it receives (1 ms later), its answers
/// kept for the client. Shared, so the test can look at the core's configuration.
#[derive(Clone)]
struct Robot {
    core: Arc<Mutex<(Controller, u64)>>,
    answers: Arc<Mutex<VecDeque<CanFrame>>>,
    requests: Arc<Mutex<u32>>,
}

impl Robot {
    fn new() -> Self {
        let controller = Controller::new(&Config::dji_m3508_example()).unwrap();
        Self {
            core: Arc::new(Mutex::new((controller, 0))),
            answers: Arc::default(),
            requests: Arc::default(),
        }
    }

    fn kp(&self) -> f32 {
        self.core.lock().unwrap().0.config().gains.kp
    }
}

impl FramePort for Robot {
    fn send(&mut self, frame: &CanFrame) -> std::io::Result<()> {
        *self.requests.lock().unwrap() += 1;
        let mut core = self.core.lock().unwrap();
        let (controller, t_us) = &mut *core;
        *t_us += 1000;
        controller.on_frame(Instant::from_micros(*t_us), frame);
        let sent = controller.step(Instant::from_micros(*t_us));
        self.answers.lock().unwrap().extend(sent);
        Ok(())
    }

    fn recv_timeout(&mut self, _: Duration) -> std::io::Result<Option<CanFrame>> {
        Ok(self.answers.lock().unwrap().pop_front())
    }
}

fn serve(robot: &Robot) -> LiveServer {
    let node = NodeId::new(params::service_node(&Config::dji_m3508_example())).unwrap();
    let link = SdoClient::new(robot.clone(), node);
    LiveServer::start_with(
        "127.0.0.1:0".parse().unwrap(),
        LiveOptions::default(),
        Some(Box::new(link)),
    )
    .unwrap()
}

/// The next text message that is not `advertise`.
async fn next_answer(ws: &mut Ws) -> Value {
    loop {
        let v = next_json(ws).await;
        if v["op"] != "advertise" {
            return v;
        }
    }
}

async fn connected(server: &LiveServer) -> Ws {
    connect(server, live::SUBPROTOCOL).await.unwrap().0
}

async fn send(ws: &mut Ws, v: Value) {
    ws.send(Message::text(v.to_string())).await.unwrap();
}

fn values(answer: &Value) -> Vec<(String, Value)> {
    assert_eq!(answer["op"], "parameterValues", "{answer}");
    answer["parameters"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| (p["name"].as_str().unwrap().to_string(), p["value"].clone()))
        .collect()
}

#[tokio::test]
async fn a_client_reads_sets_and_is_told_a_refusal_with_the_value_kept() {
    let robot = Robot::new();
    let server = serve(&robot);
    let mut ws = connected(&server).await;
    let info = next_answer(&mut ws).await;
    assert_eq!(info["op"], "serverInfo");
    assert_eq!(info["capabilities"], json!(["parameters"]), "{info}");

    // Every parameter this configuration has, in the table's order, each of its type.
    send(
        &mut ws,
        json!({"op": "getParameters", "parameterNames": [], "id": "all"}),
    )
    .await;
    let all = next_answer(&mut ws).await;
    assert_eq!(all["id"], "all");
    let got = values(&all);
    let config = Config::dji_m3508_example();
    let expected: Vec<&str> = params::PARAMS
        .iter()
        .filter(|p| p.read(&config).is_ok())
        .map(|p| p.name)
        .collect();
    assert_eq!(
        got.iter().map(|(n, _)| n.as_str()).collect::<Vec<_>>(),
        expected
    );
    let kp = got.iter().find(|(n, _)| n == "gains.kp").unwrap();
    assert_eq!(kp.1, json!(1.2), "the f32's shortest decimal");

    // A set: answered with the value in force, which the core runs.
    send(
        &mut ws,
        json!({"op": "setParameters", "parameters": [{"name": "gains.kp", "value": 1.5}], "id": "s1"}),
    )
    .await;
    let set = next_answer(&mut ws).await;
    assert_eq!(set["id"], "s1");
    assert_eq!(values(&set), vec![("gains.kp".to_string(), json!(1.5))]);
    assert!((robot.kp() - 1.5).abs() < f32::EPSILON);

    // A refused value: a status naming parameter, value and rule, then the answer with the
    // old value; the core keeps 1.5. An unknown name is refused before anything is sent.
    let before = *robot.requests.lock().unwrap();
    send(
        &mut ws,
        json!({"op": "setParameters", "parameters": [
            {"name": "gains.kp", "value": 1000.0}, {"name": "gains.kq", "value": 1.0}
        ], "id": "s2"}),
    )
    .await;
    // The statuses come first, then the answer.
    let high = params::find("gains.kp").unwrap().high;
    for expected in [
        format!("gains.kp = 1000: above {high} (SDO abort 0x06090031); the value in force is kept"),
        "gains.kq: no such parameter".to_string(),
    ] {
        let status = next_answer(&mut ws).await;
        assert_eq!(status["op"], "status");
        assert_eq!(status["level"], 2, "{status}");
        assert_eq!(status["message"], expected);
    }
    let refused = next_answer(&mut ws).await;
    assert_eq!(refused["id"], "s2");
    assert_eq!(values(&refused), vec![("gains.kp".to_string(), json!(1.5))]);
    assert!((robot.kp() - 1.5).abs() < f32::EPSILON);
    assert_eq!(
        *robot.requests.lock().unwrap() - before,
        2,
        "the refused write and its read-back; nothing for the unknown name"
    );
    let _ = server.stop();
}

#[tokio::test]
async fn a_server_without_parameters_declares_none_and_says_so() {
    let server = LiveServer::start("127.0.0.1:0".parse().unwrap(), LiveOptions::default()).unwrap();
    let mut ws = connected(&server).await;
    let info = next_answer(&mut ws).await;
    assert_eq!(info["capabilities"], json!([]), "{info}");
    send(
        &mut ws,
        json!({"op": "getParameters", "parameterNames": []}),
    )
    .await;
    let status = next_answer(&mut ws).await;
    assert_eq!(status["level"], 1, "a warning: {status}");
    assert!(
        status["message"]
            .as_str()
            .unwrap()
            .ends_with("read-only): getParameters"),
        "{status}"
    );
    let _ = server.stop();
}
