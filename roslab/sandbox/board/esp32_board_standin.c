/*
 * roslab sandbox STAND-IN for the ESP32 board of robot profile esp32_microros.
 *
 * A real board runs firmware/esp32_microros (micro-ROS on the ESP32): it publishes its
 * potentiometer reading, std_msgs/Int32 on /esp32/potentiometer, through the micro-ROS agent
 * on the host it is plugged into. No ESP32 exists here, so this Linux program speaks the same
 * protocol (DDS-XRCE, with eProsima's Micro-XRCE-DDS-Client and Micro-CDR, the libraries the
 * board's firmware is built on) over UDP to the REAL agent, and publishes a reading that sweeps
 * 0..4095 twice a second: the team's hosts hear it as they would hear the board.
 *
 * usage: esp32_board_standin AGENT_IP AGENT_PORT DOMAIN_ID
 * It runs until killed; it exits 1 when the agent cannot be reached or refuses the entities.
 */
#include <uxr/client/client.h>
#include <ucdr/microcdr.h>

#include <stdio.h>
#include <stdlib.h>

#define STREAM_HISTORY 8
#define BUFFER_SIZE (UXR_CONFIG_UDP_TRANSPORT_MTU * STREAM_HISTORY)

int main(int argc, char **argv)
{
    if (argc != 4) {
        fprintf(stderr, "usage: %s AGENT_IP AGENT_PORT DOMAIN_ID\n", argv[0]);
        return 2;
    }
    setvbuf(stdout, NULL, _IOLBF, 0);
    uxrUDPTransport transport;
    if (!uxr_init_udp_transport(&transport, UXR_IPv4, argv[1], argv[2])) {
        fprintf(stderr, "esp32 stand-in: cannot open UDP to %s:%s\n", argv[1], argv[2]);
        return 1;
    }
    uxrSession session;
    uxr_init_session(&session, &transport.comm, 0xE5320001);
    if (!uxr_create_session(&session)) {
        fprintf(stderr, "esp32 stand-in: no micro-ROS agent answers on %s:%s\n", argv[1], argv[2]);
        return 1;
    }
    uint8_t out_buffer[BUFFER_SIZE];
    uxrStreamId out = uxr_create_output_reliable_stream(&session, out_buffer, BUFFER_SIZE, STREAM_HISTORY);
    uint8_t in_buffer[BUFFER_SIZE];
    uxr_create_input_reliable_stream(&session, in_buffer, BUFFER_SIZE, STREAM_HISTORY);

    /* What rclc creates for the firmware's node and publisher: a participant in the class's
     * ROS_DOMAIN_ID, the topic as ROS 2 names it in DDS (rt/ prefix, dds_ type), a writer with
     * ROS 2's default QoS (reliable, volatile, keep last 10). */
    uxrObjectId participant = uxr_object_id(0x01, UXR_PARTICIPANT_ID);
    uxrObjectId topic = uxr_object_id(0x01, UXR_TOPIC_ID);
    uxrObjectId publisher = uxr_object_id(0x01, UXR_PUBLISHER_ID);
    uxrObjectId writer = uxr_object_id(0x01, UXR_DATAWRITER_ID);
    uxrQoS_t qos = {.reliability = UXR_RELIABILITY_RELIABLE, .durability = UXR_DURABILITY_VOLATILE,
                    .history = UXR_HISTORY_KEEP_LAST, .depth = 10};
    uint16_t requests[] = {
        uxr_buffer_create_participant_bin(&session, out, participant, (int16_t)atoi(argv[3]), "esp32_board",
                                          UXR_REPLACE),
        uxr_buffer_create_topic_bin(&session, out, topic, participant, "rt/esp32/potentiometer",
                                    "std_msgs::msg::dds_::Int32_", UXR_REPLACE),
        uxr_buffer_create_publisher_bin(&session, out, publisher, participant, UXR_REPLACE),
        uxr_buffer_create_datawriter_bin(&session, out, writer, publisher, topic, qos, UXR_REPLACE),
    };
    uint8_t status[sizeof(requests) / sizeof(requests[0])];
    if (!uxr_run_session_until_all_status(&session, 5000, requests, status, sizeof(status))) {
        fprintf(stderr, "esp32 stand-in: the agent refused the board's entities (status %u %u %u %u)\n",
                status[0], status[1], status[2], status[3]);
        return 1;
    }
    printf("esp32 stand-in: publishing /esp32/potentiometer through the agent at %s:%s (domain %s)\n",
           argv[1], argv[2], argv[3]);
    for (int32_t reading = 0;; reading = (reading + 273) % 4096) {
        ucdrBuffer ub;
        uxr_prepare_output_stream(&session, out, writer, &ub, 4);
        ucdr_serialize_int32_t(&ub, reading);
        if (!uxr_run_session_time(&session, 500)) {
            /* a reliable stream not acknowledged in time: the agent went away */
            fprintf(stderr, "esp32 stand-in: the agent stopped answering\n");
        }
    }
}
