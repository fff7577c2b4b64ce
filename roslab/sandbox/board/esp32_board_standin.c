/*
 * roslab sandbox STAND-IN for the ESP32 board of robot profile esp32_microros.
 *
 * A real board runs firmware/esp32_microros (micro-ROS on the ESP32): its node publishes the
 * potentiometer reading, std_msgs/Int32 on /esp32/potentiometer, and subscribes to the servo
 * angle, std_msgs/Int32 on /esp32/servo_angle, through the micro-ROS agent on the host it is
 * attached to. No ESP32 exists here, so this Linux program speaks the same protocol (DDS-XRCE,
 * with eProsima's Micro-XRCE-DDS-Client and Micro-CDR, the libraries the board's firmware is
 * built on) over UDP to the REAL agent, and publishes a reading that sweeps 0..4095 ten times a
 * second, as often as the firmware publishes: the team's hosts hear it as they would the board.
 *
 * It is flashed as the firmware is: the same environment variables give its ROS domain and its
 * node name (ROSLAB_ROS_DOMAIN_ID, ROSLAB_NODE_NAME) and the agent's address and port
 * (ROSLAB_AGENT_IP, ROSLAB_AGENT_PORT); roslab/robot_tools/esp32_firmware.py computes them from
 * the roster for both. And it reconnects as the firmware does (its loop's states): wait for the
 * agent (a ping every 500 ms), create the session and the node's entities, ping the agent while
 * publishing, and when a ping fails (the agent was killed, its host rebooted) drop the session
 * and wait again. tests/unit/test_esp32_board.py holds this file and the firmware together.
 *
 * usage: ROSLAB_ROS_DOMAIN_ID=N ROSLAB_NODE_NAME=NAME ROSLAB_AGENT_IP=IP ROSLAB_AGENT_PORT=PORT
 *        esp32_board_standin
 * It runs until killed; it exits 2 when a variable is missing or wrong.
 */
#include <uxr/client/client.h>
#include <uxr/client/util/ping.h>
#include <ucdr/microcdr.h>

#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#define STREAM_HISTORY 8
#define BUFFER_SIZE (UXR_CONFIG_UDP_TRANSPORT_MTU * STREAM_HISTORY)
#define PUBLISH_PERIOD_MS 100 /* the firmware's kPublishPeriodMs */
#define PING_TIMEOUT_MS 100   /* the firmware's kAgentPingTimeoutMs */
#define WAIT_MS 500           /* the firmware's delay while waiting for the agent */

static const char *required(const char *name)
{
    const char *value = getenv(name);
    if (value == NULL || value[0] == '\0') {
        fprintf(stderr, "esp32 stand-in: %s is not set (roslab esp32-firmware prints the board's values)\n", name);
        exit(2);
    }
    return value;
}

static void sleep_ms(long ms)
{
    struct timespec pause = {ms / 1000, (ms % 1000) * 1000000L};
    nanosleep(&pause, NULL);
}

struct board {
    uxrUDPTransport transport;
    uxrSession session;
    uxrStreamId out;
    uxrObjectId writer;
    uint8_t out_buffer[BUFFER_SIZE];
    uint8_t in_buffer[BUFFER_SIZE];
};

/* What rclc creates for the firmware's node: a participant named as the node in the team's
 * domain, the topics as ROS 2 names them in DDS (rt/ prefix, dds_ type), a writer and a reader
 * with ROS 2's default QoS (reliable, volatile, keep last 10). */
static int create_entities(struct board *board, int16_t domain, const char *node)
{
    uxr_init_session(&board->session, &board->transport.comm, 0xE5320001);
    if (!uxr_create_session(&board->session)) {
        return 0;
    }
    board->out = uxr_create_output_reliable_stream(&board->session, board->out_buffer, BUFFER_SIZE, STREAM_HISTORY);
    uxr_create_input_reliable_stream(&board->session, board->in_buffer, BUFFER_SIZE, STREAM_HISTORY);
    uxrObjectId participant = uxr_object_id(0x01, UXR_PARTICIPANT_ID);
    uxrObjectId reading = uxr_object_id(0x01, UXR_TOPIC_ID), angle = uxr_object_id(0x02, UXR_TOPIC_ID);
    uxrObjectId publisher = uxr_object_id(0x01, UXR_PUBLISHER_ID);
    uxrObjectId subscriber = uxr_object_id(0x01, UXR_SUBSCRIBER_ID);
    uxrObjectId reader = uxr_object_id(0x01, UXR_DATAREADER_ID);
    board->writer = uxr_object_id(0x01, UXR_DATAWRITER_ID);
    uxrQoS_t qos = {.reliability = UXR_RELIABILITY_RELIABLE, .durability = UXR_DURABILITY_VOLATILE,
                    .history = UXR_HISTORY_KEEP_LAST, .depth = 10};
    uxrSession *s = &board->session;
    uint16_t requests[] = {
        uxr_buffer_create_participant_bin(s, board->out, participant, domain, node, UXR_REPLACE),
        uxr_buffer_create_topic_bin(s, board->out, reading, participant, "rt/esp32/potentiometer",
                                    "std_msgs::msg::dds_::Int32_", UXR_REPLACE),
        uxr_buffer_create_publisher_bin(s, board->out, publisher, participant, UXR_REPLACE),
        uxr_buffer_create_datawriter_bin(s, board->out, board->writer, publisher, reading, qos, UXR_REPLACE),
        uxr_buffer_create_topic_bin(s, board->out, angle, participant, "rt/esp32/servo_angle",
                                    "std_msgs::msg::dds_::Int32_", UXR_REPLACE),
        uxr_buffer_create_subscriber_bin(s, board->out, subscriber, participant, UXR_REPLACE),
        uxr_buffer_create_datareader_bin(s, board->out, reader, subscriber, angle, qos, UXR_REPLACE),
    };
    uint8_t status[sizeof(requests) / sizeof(requests[0])];
    if (!uxr_run_session_until_all_status(s, 5000, requests, status, sizeof(status))) {
        fprintf(stderr, "esp32 stand-in: the agent refused the board's entities\n");
        return 0;
    }
    return 1;
}

int main(void)
{
    const char *domain_text = required("ROSLAB_ROS_DOMAIN_ID"), *node = required("ROSLAB_NODE_NAME");
    const char *address = required("ROSLAB_AGENT_IP"), *port = required("ROSLAB_AGENT_PORT");
    char *end;
    long domain = strtol(domain_text, &end, 10);
    if (*end != '\0' || domain < 0 || domain > 232) {
        fprintf(stderr, "esp32 stand-in: ROSLAB_ROS_DOMAIN_ID=%s is not a ROS domain (0-232)\n", domain_text);
        return 2;
    }
    setvbuf(stdout, NULL, _IOLBF, 0);
    static struct board board;
    if (!uxr_init_udp_transport(&board.transport, UXR_IPv4, address, port)) {
        fprintf(stderr, "esp32 stand-in: cannot open UDP to %s:%s\n", address, port);
        return 1;
    }
    printf("esp32 stand-in: node %s, domain %ld, waiting for the agent at %s:%s\n", node, domain, address, port);
    int32_t reading = 0;
    for (;;) {
        /* waiting for the agent */
        if (!uxr_ping_agent_attempts(&board.transport.comm, PING_TIMEOUT_MS, 1)) {
            sleep_ms(WAIT_MS);
            continue;
        }
        if (!create_entities(&board, (int16_t)domain, node)) {
            sleep_ms(WAIT_MS);
            continue;
        }
        printf("esp32 stand-in: publishing /esp32/potentiometer through the agent at %s:%s (domain %ld, node %s)\n",
               address, port, domain, node);
        /* connected: publish, and ping the agent each period */
        while (uxr_ping_agent_session(&board.session, PING_TIMEOUT_MS, 1)) {
            ucdrBuffer ub;
            uxr_prepare_output_stream(&board.session, board.out, board.writer, &ub, 4);
            ucdr_serialize_int32_t(&ub, reading);
            reading = (reading + 273) % 4096;
            uxr_run_session_time(&board.session, PUBLISH_PERIOD_MS);
        }
        /* lost: drop the session without waiting for the agent (it is gone), wait again */
        printf("esp32 stand-in: the agent stopped answering; waiting for it again\n");
        uxr_delete_session_retries(&board.session, 0);
    }
}
