// roslab's ESP32 micro-ROS demo firmware (robot profile esp32_microros; seed 000's circuit).
//
// Publishes the potentiometer's raw 12-bit reading (0-4095) on /esp32/potentiometer
// (std_msgs/Int32) ten times a second, and turns the servo to each angle (0-180) that arrives
// on /esp32/servo_angle (std_msgs/Int32), which roslab_esp32's servo_follower node publishes
// on the Pi. When the agent goes away (the Pi reboots, the cable is pulled, the agent is
// killed) the board waits for it and connects again, so the demo heals without a reset: the
// state machine of micro_ros_platformio's examples/ethernet_pubsub (ping the agent; create the
// entities; ping while connected; destroy them when a ping fails; wait again).
//
// The team's ROS domain (ROSLAB_ROS_DOMAIN_ID) and the board's node name (ROSLAB_NODE_NAME,
// esp32_board_<team>) come from the build's environment (platformio.ini); `roslab
// esp32-firmware` prints them for each team. The domain is set on rcl's init options: the
// micro-ROS agent's XRCE_DOMAIN_ID_OVERRIDE applies only to a board that asks for domain 255.
//
// It cannot be compiled here (roslab's controller): see README.md for building and flashing.

#include <Arduino.h>
#include <ESP32Servo.h>
#include <micro_ros_platformio.h>
#include <rcl/rcl.h>
#include <rclc/executor.h>
#include <rclc/rclc.h>
#include <std_msgs/msg/int32.h>

#if defined(ROSLAB_TRANSPORT_UDP)
#include <WiFi.h>
#endif

namespace {

constexpr bool all_digits(const char *text) {
  return *text == '\0' || (*text >= '0' && *text <= '9' && all_digits(text + 1));
}
constexpr unsigned long parsed(const char *text, unsigned long value) {
  return *text == '\0' ? value : parsed(text + 1, value * 10 + (*text - '0'));
}

static_assert(ROSLAB_ROS_DOMAIN_ID[0] != '\0' && all_digits(ROSLAB_ROS_DOMAIN_ID),
              "set ROSLAB_ROS_DOMAIN_ID to the team's ROS domain (roslab esp32-firmware prints it)");
static_assert(ROSLAB_NODE_NAME[0] != '\0',
              "set ROSLAB_NODE_NAME to the board's node name (roslab esp32-firmware prints it)");
constexpr size_t kDomainId = parsed(ROSLAB_ROS_DOMAIN_ID, 0);
static_assert(kDomainId <= 232, "ROSLAB_ROS_DOMAIN_ID is not a ROS domain (0-232)");
#if defined(ROSLAB_TRANSPORT_UDP)
static_assert(ROSLAB_AGENT_PORT[0] != '\0' && all_digits(ROSLAB_AGENT_PORT) &&
                  parsed(ROSLAB_AGENT_PORT, 0) <= 65535,
              "set ROSLAB_AGENT_PORT to the agent's UDP port (the roster's esp32_udp_port)");
#endif

constexpr int kPublishPeriodMs = 100;
constexpr int kAgentPingTimeoutMs = 100;

Servo servo;
rcl_allocator_t allocator;
rclc_support_t support;
rcl_node_t node;
rcl_publisher_t potentiometer_publisher;
rcl_subscription_t servo_subscription;
rcl_timer_t timer;
rclc_executor_t executor;
std_msgs__msg__Int32 potentiometer_msg;
std_msgs__msg__Int32 servo_msg;

enum class Link { kWaitingForAgent, kConnected, kLost };
Link link = Link::kWaitingForAgent;

void publish_reading(rcl_timer_t *, int64_t) {
  potentiometer_msg.data = analogRead(POTENTIOMETER_PIN);
  (void)rcl_publish(&potentiometer_publisher, &potentiometer_msg, nullptr);
}

void on_servo_angle(const void *message) {
  const auto *angle = static_cast<const std_msgs__msg__Int32 *>(message);
  servo.write(constrain(angle->data, 0, 180));
}

bool create_entities() {
  allocator = rcl_get_default_allocator();
  rcl_init_options_t init_options = rcl_get_zero_initialized_init_options();
  if (rcl_init_options_init(&init_options, allocator) != RCL_RET_OK) return false;
  if (rcl_init_options_set_domain_id(&init_options, kDomainId) != RCL_RET_OK) return false;
  const bool supported =
      rclc_support_init_with_options(&support, 0, nullptr, &init_options, &allocator) == RCL_RET_OK;
  (void)rcl_init_options_fini(&init_options);
  if (!supported) return false;
  if (rclc_node_init_default(&node, ROSLAB_NODE_NAME, "", &support) != RCL_RET_OK) return false;
  if (rclc_publisher_init_default(&potentiometer_publisher, &node,
                                  ROSIDL_GET_MSG_TYPE_SUPPORT(std_msgs, msg, Int32),
                                  "esp32/potentiometer") != RCL_RET_OK) return false;
  if (rclc_subscription_init_default(&servo_subscription, &node,
                                     ROSIDL_GET_MSG_TYPE_SUPPORT(std_msgs, msg, Int32),
                                     "esp32/servo_angle") != RCL_RET_OK) return false;
  if (rclc_timer_init_default(&timer, &support, RCL_MS_TO_NS(kPublishPeriodMs),
                              publish_reading) != RCL_RET_OK) return false;
  executor = rclc_executor_get_zero_initialized_executor();
  if (rclc_executor_init(&executor, &support.context, 2, &allocator) != RCL_RET_OK) return false;
  if (rclc_executor_add_timer(&executor, &timer) != RCL_RET_OK) return false;
  return rclc_executor_add_subscription(&executor, &servo_subscription, &servo_msg,
                                        &on_servo_angle, ON_NEW_DATA) == RCL_RET_OK;
}

void destroy_entities() {
  rmw_context_t *context = rcl_context_get_rmw_context(&support.context);
  (void)rmw_uros_set_context_entity_destroy_session_timeout(context, 0);
  (void)rcl_publisher_fini(&potentiometer_publisher, &node);
  (void)rcl_subscription_fini(&servo_subscription, &node);
  (void)rcl_timer_fini(&timer);
  (void)rclc_executor_fini(&executor);
  (void)rcl_node_fini(&node);
  (void)rclc_support_fini(&support);
}

}  // namespace

void setup() {
#if defined(ROSLAB_TRANSPORT_UDP)
  IPAddress agent;
  agent.fromString(ROSLAB_AGENT_IP);
  set_microros_wifi_transports(const_cast<char *>(ROSLAB_WIFI_SSID),
                               const_cast<char *>(ROSLAB_WIFI_PASSWORD), agent,
                               parsed(ROSLAB_AGENT_PORT, 0));
#else
  Serial.begin(115200);
  set_microros_serial_transports(Serial);
#endif
  analogReadResolution(12);
  servo.attach(SERVO_PIN);
  servo.write(90);
}

void loop() {
  switch (link) {
    case Link::kWaitingForAgent:
      if (rmw_uros_ping_agent(kAgentPingTimeoutMs, 1) == RMW_RET_OK) {
        link = create_entities() ? Link::kConnected : Link::kLost;
      } else {
        delay(500);
      }
      break;
    case Link::kConnected:
      if (rmw_uros_ping_agent(kAgentPingTimeoutMs, 1) != RMW_RET_OK) {
        link = Link::kLost;
      } else {
        rclc_executor_spin_some(&executor, RCL_MS_TO_NS(10));
      }
      break;
    case Link::kLost:
      destroy_entities();
      link = Link::kWaitingForAgent;
      break;
  }
}
