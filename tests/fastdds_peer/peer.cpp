// A ROS 2 node's view of rtloop over Fast DDS (ROS 2's default DDS), without ROS 2:
//   peer DOMAIN ANGLES_TOPIC SETPOINT_TOPIC COUNT TIMEOUT_S SETPOINT...
// Subscribes to JointState with ROS 2's default QoS (reliable, volatile, keep last 10) and
// prints "ANGLES name=value ..." per message; publishes Float64MultiArray SETPOINT every
// 50 ms with the same QoS. Exits after COUNT messages or TIMEOUT_S seconds.
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <thread>
#include <vector>

#include <fastdds/dds/domain/DomainParticipant.hpp>
#include <fastdds/dds/domain/DomainParticipantFactory.hpp>
#include <fastdds/dds/publisher/DataWriter.hpp>
#include <fastdds/dds/publisher/Publisher.hpp>
#include <fastdds/dds/subscriber/DataReader.hpp>
#include <fastdds/dds/subscriber/SampleInfo.hpp>
#include <fastdds/dds/subscriber/Subscriber.hpp>

#include "ros2_typesPubSubTypes.h"

using namespace eprosima::fastdds::dds;

template <typename Qos>
Qos ros2_default(Qos qos) {
    qos.reliability().kind = RELIABLE_RELIABILITY_QOS;
    qos.durability().kind = VOLATILE_DURABILITY_QOS;
    qos.history().kind = KEEP_LAST_HISTORY_QOS;
    qos.history().depth = 10;
    return qos;
}

int main(int argc, char** argv) {
    if (argc < 7) {
        std::fprintf(stderr, "usage: peer DOMAIN ANGLES_TOPIC SETPOINT_TOPIC COUNT TIMEOUT_S SETPOINT...\n");
        return 2;
    }
    const int domain = std::atoi(argv[1]);
    const int count = std::atoi(argv[4]);
    const double timeout_s = std::atof(argv[5]);
    std::vector<double> setpoint;
    for (int i = 6; i < argc; ++i) setpoint.push_back(std::atof(argv[i]));

    DomainParticipant* participant =
        DomainParticipantFactory::get_instance()->create_participant(domain, PARTICIPANT_QOS_DEFAULT);
    TypeSupport joint_state(new sensor_msgs::msg::dds_::JointState_PubSubType());
    TypeSupport multi_array(new std_msgs::msg::dds_::Float64MultiArray_PubSubType());
    joint_state.register_type(participant);
    multi_array.register_type(participant);
    Topic* angles = participant->create_topic(argv[2], joint_state.get_type_name(), TOPIC_QOS_DEFAULT);
    Topic* setpoints = participant->create_topic(argv[3], multi_array.get_type_name(), TOPIC_QOS_DEFAULT);
    DataReader* reader = participant->create_subscriber(SUBSCRIBER_QOS_DEFAULT)
                             ->create_datareader(angles, ros2_default(DATAREADER_QOS_DEFAULT));
    DataWriter* writer = participant->create_publisher(PUBLISHER_QOS_DEFAULT)
                             ->create_datawriter(setpoints, ros2_default(DATAWRITER_QOS_DEFAULT));
    std::printf("READY %s %s\n", joint_state.get_type_name().c_str(), multi_array.get_type_name().c_str());
    std::fflush(stdout);

    std_msgs::msg::dds_::Float64MultiArray_ message;
    message.data(setpoint);
    int received = 0;
    const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(timeout_s);
    while (received < count && std::chrono::steady_clock::now() < end) {
        writer->write(&message);
        Duration_t wait(0, 50000000);
        reader->wait_for_unread_message(wait);
        sensor_msgs::msg::dds_::JointState_ sample;
        SampleInfo info;
        while (reader->take_next_sample(&sample, &info) == ReturnCode_t::RETCODE_OK) {
            if (!info.valid_data) continue;
            ++received;
            std::printf("ANGLES");
            for (size_t i = 0; i < sample.name().size() && i < sample.position().size(); ++i)
                std::printf(" %s=%.17g", sample.name()[i].c_str(), sample.position()[i]);
            std::printf("\n");
        }
        std::fflush(stdout);
    }
    std::printf("DONE %d\n", received);
    std::fflush(stdout);
    participant->delete_contained_entities();
    DomainParticipantFactory::get_instance()->delete_participant(participant);
    return 0;
}
